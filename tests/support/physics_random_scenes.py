"""Random valid scenes of the shared size, built on the device: numpy draws the parameters (fixed seed), and one
jitted, vmapped builder turns each row of parameters into a scene with the engine's own helpers.

Each scene has the arena, up to 4 boxes or triangles, up to 3 circles (some of them fixed), up to 2 joints
(revolute with or without motor and limits, or fixed) between two random active bodies, anchored at the midpoint
of their centres so the joint starts satisfied, and up to 2 thrusters on random active bodies.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.physics import (
    SimState,
    add_circle,
    add_fixed_joint,
    add_polygon,
    add_revolute_joint,
    add_thruster,
)
from impulse.engine.physics.geometry import rotate
from tests.support.physics_sim import SIZES, arena_scene

NUM_FREE_POLYGONS = SIZES.num_polygons - SIZES.num_static_polygons
NUM_CIRCLES = SIZES.num_circles


def draw_parameters(num_scenes: int, seed: int) -> dict[str, np.ndarray]:
    """Every random number the builder needs, one row per scene."""
    rng = np.random.default_rng(seed)
    P, C, J, T = NUM_FREE_POLYGONS, NUM_CIRCLES, SIZES.num_joints, SIZES.num_thrusters

    def u(low: float, high: float, *shape: int) -> np.ndarray:
        return rng.uniform(low, high, (num_scenes, *shape)).astype(np.float32)

    # A triangle's vertices sit at angles 90, -30, -150 degrees (clockwise) +-20 degrees, radius 0.1..0.4 m.
    base = np.radians([90.0, -30.0, -150.0])
    tri_angle = base + rng.uniform(-0.35, 0.35, (num_scenes, P, 3))
    tri_radius = rng.uniform(0.1, 0.4, (num_scenes, P, 3))
    tri = np.stack([tri_radius * np.cos(tri_angle), tri_radius * np.sin(tri_angle)], axis=-1)
    return {
        "poly_used": rng.random((num_scenes, P)) < 0.85,
        "poly_triangle": rng.random((num_scenes, P)) < 0.3,
        "poly_position": np.stack([u(0.4, 4.6, P), u(0.7, 4.5, P)], axis=-1),
        "poly_size": u(0.1, 0.8, P, 2),
        "poly_triangle_vertices": tri.astype(np.float32),
        "poly_rotation": u(-np.pi, np.pi, P),
        "poly_velocity": u(-2.0, 2.0, P, 2),
        "poly_angular_velocity": u(-3.0, 3.0, P),
        "poly_density": u(0.5, 3.0, P),
        "poly_friction": u(0.0, 1.0, P),
        "poly_restitution": u(0.0, 0.8, P),
        "poly_fixed": rng.random((num_scenes, P)) < 0.15,
        "circle_used": rng.random((num_scenes, C)) < 0.8,
        "circle_position": np.stack([u(0.4, 4.6, C), u(0.7, 4.5, C)], axis=-1),
        "circle_radius": u(0.05, 0.4, C),
        "circle_velocity": u(-2.0, 2.0, C, 2),
        "circle_density": u(0.5, 3.0, C),
        "circle_friction": u(0.0, 1.0, C),
        "circle_restitution": u(0.0, 0.8, C),
        "circle_fixed": rng.random((num_scenes, C)) < 0.15,
        "joint_used": rng.random((num_scenes, J)) < 0.7,
        "joint_pick": u(0.0, 1.0, J, SIZES.num_bodies),
        "joint_fixed": rng.random((num_scenes, J)) < 0.3,
        "joint_motor": rng.random((num_scenes, J)) < 0.5,
        "joint_speed": u(0.5, 2.0, J),
        "joint_power": u(0.5, 2.0, J),
        "joint_limits": rng.random((num_scenes, J)) < 0.3,
        "joint_min": u(-1.5, -0.1, J),
        "joint_max": u(0.1, 1.5, J),
        "thruster_used": rng.random((num_scenes, T)) < 0.7,
        "thruster_pick": u(0.0, 1.0, T, SIZES.num_bodies),
        "thruster_offset": u(-0.1, 0.1, T, 2),
        "thruster_rotation": u(-np.pi, np.pi, T),
        "thruster_power": u(0.5, 2.0, T),
    }


def _select(flag, when_true: SimState, when_false: SimState) -> SimState:
    return jax.tree.map(lambda a, b: jnp.where(flag, a, b), when_true, when_false)


def _fix(state: SimState, index, fixed) -> SimState:
    """Make body `index` static when `fixed` (the helpers' `fixed` argument is a Python bool, not traceable)."""
    b = state.bodies
    keep = jnp.where(fixed, 0.0, 1.0)
    at = jnp.where(index < 0, b.active.shape[0], index)

    def scale(arr):
        return arr.at[at].multiply(keep, mode="drop")

    velocity = b.velocity.at[at].multiply(keep, mode="drop")
    return state.replace(
        bodies=b.replace(
            inverse_mass=scale(b.inverse_mass),
            inverse_inertia=scale(b.inverse_inertia),
            velocity=velocity,
            angular_velocity=scale(b.angular_velocity),
        )
    )


def _pick_active(state: SimState, scores, count: int):
    """`count` distinct active non-arena bodies, chosen by the lowest random scores; and whether there were enough."""
    movable = state.bodies.active.at[: SIZES.num_static_polygons].set(False)
    order = jnp.argsort(jnp.where(movable, scores, 2.0 + scores))
    return order[:count], movable.sum() >= count


def build_scene(p: dict) -> SimState:
    """One scene from one row of `draw_parameters` (traceable: vmap it over rows)."""
    state = arena_scene()
    for k in range(NUM_FREE_POLYGONS):
        common = {
            "rotation": p["poly_rotation"][k],
            "velocity": p["poly_velocity"][k],
            "angular_velocity": p["poly_angular_velocity"][k],
            "density": p["poly_density"][k],
            "friction": p["poly_friction"][k],
            "restitution": p["poly_restitution"][k],
        }
        position = p["poly_position"][k]
        w, h = p["poly_size"][k, 0], p["poly_size"][k, 1]
        # add_rectangle builds its vertices with numpy, so traced sizes go through add_polygon.
        box_vertices = (
            jnp.stack([jnp.stack([-w, h]), jnp.stack([w, h]), jnp.stack([w, -h]), jnp.stack([-w, -h])]) / 2
        )
        box_state, box_index = add_polygon(state, position, box_vertices, **common)
        tri_state, tri_index = add_polygon(state, position, p["poly_triangle_vertices"][k], **common)
        added = _select(p["poly_triangle"][k], tri_state, box_state)
        index = jnp.where(p["poly_triangle"][k], tri_index, box_index)
        added = _fix(added, index, p["poly_fixed"][k])
        state = _select(p["poly_used"][k], added, state)
    for k in range(NUM_CIRCLES):
        added, index = add_circle(
            state,
            p["circle_position"][k],
            p["circle_radius"][k],
            velocity=p["circle_velocity"][k],
            density=p["circle_density"][k],
            friction=p["circle_friction"][k],
            restitution=p["circle_restitution"][k],
        )
        added = _fix(added, index, p["circle_fixed"][k])
        state = _select(p["circle_used"][k], added, state)
    for k in range(SIZES.num_joints):
        (a, b), enough = _pick_active(state, p["joint_pick"][k], 2)
        pos, rot = state.bodies.position, state.bodies.rotation
        middle = (pos[a] + pos[b]) / 2
        a_rel, b_rel = rotate(-rot[a], middle - pos[a]), rotate(-rot[b], middle - pos[b])
        revolute, _ = add_revolute_joint(
            state,
            a,
            b,
            a_rel,
            b_rel,
            motor_on=p["joint_motor"][k],
            motor_speed=p["joint_speed"][k],
            motor_power=p["joint_power"][k],
            has_joint_limits=p["joint_limits"][k],
            min_rotation=p["joint_min"][k],
            max_rotation=p["joint_max"][k],
        )
        fixed, _ = add_fixed_joint(state, a, b, a_rel, b_rel)
        added = _select(p["joint_fixed"][k], fixed, revolute)
        state = _select(p["joint_used"][k] & enough, added, state)
    for k in range(SIZES.num_thrusters):
        (body,), enough = _pick_active(state, p["thruster_pick"][k], 1)
        added, _ = add_thruster(
            state, body, p["thruster_offset"][k], p["thruster_rotation"][k], p["thruster_power"][k]
        )
        state = _select(p["thruster_used"][k] & enough, added, state)
    return state


@functools.cache
def _batched_builder():
    return jax.jit(jax.vmap(build_scene))


def build_scenes(params: dict[str, np.ndarray]) -> SimState:
    """A batch of scenes (leading axis = scene), built in one compiled call."""
    return _batched_builder()({k: jnp.asarray(v) for k, v in params.items()})


def draw_actions(num_scenes: int, num_steps: int, seed: int) -> np.ndarray:
    """[scenes, steps, actions]: motor actions in [-1, 1], thruster actions in [0, 1]."""
    rng = np.random.default_rng(seed)
    motors = rng.uniform(-1.0, 1.0, (num_scenes, num_steps, SIZES.num_joints))
    thrusters = rng.uniform(0.0, 1.0, (num_scenes, num_steps, SIZES.num_thrusters))
    return np.concatenate([motors, thrusters], axis=-1).astype(np.float32)
