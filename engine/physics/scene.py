"""Building scenes: the empty arena and helpers that add shapes, joints and thrusters.

Each helper is a pure function of the state (jittable; the slot used is the first inactive one, and the slot
index is returned), so the level generator can build scenes on the device. A full array is reported by the
validator rather than silently ignored: the helpers return index -1 when no slot is free.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from engine.physics.mass import MassConvention, circle_mass_properties, polygon_mass_properties
from engine.physics.pairs import pair_tables
from engine.physics.sizes import SceneSizes
from engine.physics.state import Bodies, ContactCache, Joints, SimState, Thrusters

Array = jnp.ndarray

ARENA_SIZE = 5.0
FLOOR_TOP = 0.4


def _arena_polygons(max_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions and clockwise local vertices of floor, left wall, right wall and ceiling (Kinetix's files)."""
    def box(half_w: float, half_h: float) -> list[tuple[float, float]]:
        return [(-half_w, half_h), (half_w, half_h), (half_w, -half_h), (-half_w, -half_h)]

    positions = np.array([[2.5, -4.8], [0.0, 0.0], [0.0, 0.0], [2.5, 10.2]], dtype=np.float32)
    vertices = np.zeros((4, max_vertices, 2), dtype=np.float32)
    vertices[0, :4] = box(2.5, 5.2)
    vertices[1, :4] = [(-5.0, 5.0), (0.0, 5.0), (0.0, 0.0), (-5.0, 0.0)]
    vertices[2, :4] = [(5.0, 5.0), (10.0, 5.0), (10.0, 0.0), (5.0, 0.0)]
    vertices[3, :4] = box(2.5, 5.2)
    return positions, vertices


def empty_scene(sizes: SceneSizes, arena: bool = True) -> SimState:
    """A scene with every slot free except the static arena polygons (floor top at y = 0.4, walls at x = 0 and
    x = 5, ceiling at y = 5). With `arena=False` the arena slots exist but are inactive (an empty, open world)."""
    P, C, J, T = sizes.num_polygons, sizes.num_circles, sizes.num_joints, sizes.num_thrusters
    N, V, S = P + C, sizes.max_polygon_vertices, sizes.num_static_polygons
    tables = pair_tables(sizes)
    f32 = lambda *shape: jnp.zeros(shape, jnp.float32)  # noqa: E731
    position = np.zeros((N, 2), np.float32)
    vertices = np.zeros((P, V, 2), np.float32)
    n_vertices = np.full((P,), min(4, V), np.int32)
    mode = np.ones((N,), np.int32)
    active = np.zeros((N,), bool)
    if S:
        arena_pos, arena_vertices = _arena_polygons(V)
        count = min(S, 4)
        position[:count] = arena_pos[:count]
        vertices[:count] = arena_vertices[:count]
        mode[:S] = 2
        active[:S] = arena
    bodies = Bodies(
        position=jnp.asarray(position),
        rotation=f32(N),
        velocity=f32(N, 2),
        angular_velocity=f32(N),
        inverse_mass=f32(N),
        inverse_inertia=f32(N),
        friction=jnp.ones((N,), jnp.float32),
        restitution=f32(N),
        collision_mode=jnp.asarray(mode),
        active=jnp.asarray(active),
    )
    joints = Joints(
        a_index=jnp.zeros((J,), jnp.int32),
        b_index=jnp.zeros((J,), jnp.int32),
        a_relative_pos=f32(J, 2),
        b_relative_pos=f32(J, 2),
        rotation=f32(J),
        active=jnp.zeros((J,), bool),
        is_fixed_joint=jnp.zeros((J,), bool),
        motor_on=jnp.zeros((J,), bool),
        motor_speed=jnp.ones((J,), jnp.float32),
        motor_power=jnp.ones((J,), jnp.float32),
        motor_has_joint_limits=jnp.zeros((J,), bool),
        min_rotation=jnp.full((J,), -np.pi, jnp.float32),
        max_rotation=jnp.full((J,), np.pi, jnp.float32),
        acc_impulse=f32(J, 2),
        acc_r_impulse=f32(J),
        global_position=f32(J, 2),
    )
    thrusters = Thrusters(
        body_index=jnp.zeros((T,), jnp.int32),
        relative_position=f32(T, 2),
        rotation=f32(T),
        power=jnp.ones((T,), jnp.float32),
        active=jnp.zeros((T,), bool),
        global_position=f32(T, 2),
    )
    K = tables.num_contacts
    return SimState(
        bodies=bodies,
        polygon_vertices=jnp.asarray(vertices),
        polygon_n_vertices=jnp.asarray(n_vertices),
        circle_radius=f32(C),
        joints=joints,
        thrusters=thrusters,
        contacts=ContactCache(f32(K), f32(K), jnp.zeros((K,), bool)),
        pair_collides=jnp.ones((tables.num_pairs,), bool),
        gravity=jnp.asarray([0.0, -9.81], jnp.float32),
    )


def _free_slot(active: Array) -> Array:
    """First inactive slot, or -1 when all are taken."""
    if active.shape[0] == 0:
        return jnp.asarray(-1, jnp.int32)
    slot = jnp.argmin(active).astype(jnp.int32)
    return jnp.where(active[slot], -1, slot)


def _set_body(
    bodies: Bodies,
    index: Array,
    position: Array,
    rotation: float,
    velocity: Array,
    angular_velocity: float,
    inverse_mass: Array,
    inverse_inertia: Array,
    friction: float,
    restitution: float,
    collision_mode: int,
) -> Bodies:
    # Index -1 (no free slot) must not write: out-of-range indices are dropped by mode="drop".
    at = jnp.where(index < 0, bodies.active.shape[0], index)
    put = lambda arr, value: arr.at[at].set(value, mode="drop")  # noqa: E731
    return Bodies(
        position=put(bodies.position, position),
        rotation=put(bodies.rotation, rotation),
        velocity=put(bodies.velocity, velocity),
        angular_velocity=put(bodies.angular_velocity, angular_velocity),
        inverse_mass=put(bodies.inverse_mass, inverse_mass),
        inverse_inertia=put(bodies.inverse_inertia, inverse_inertia),
        friction=put(bodies.friction, friction),
        restitution=put(bodies.restitution, restitution),
        collision_mode=put(bodies.collision_mode, collision_mode),
        active=put(bodies.active, True),
    )


def add_polygon(
    state: SimState,
    position,
    vertices,
    rotation: float = 0.0,
    velocity=(0.0, 0.0),
    angular_velocity: float = 0.0,
    density: float = 1.0,
    friction: float = 1.0,
    restitution: float = 0.0,
    collision_mode: int = 1,
    fixed: bool = False,
    mass_convention: MassConvention = "physical",
) -> tuple[SimState, Array]:
    """Add a convex polygon given by clockwise local vertices around `position`; it is recentred on its centre of
    mass. Returns (state, body index), index -1 if all polygon slots are in use."""
    num_polygons, max_vertices = state.polygon_vertices.shape[:2]
    verts = jnp.asarray(vertices, jnp.float32)
    n = verts.shape[0]
    if not 3 <= n <= max_vertices:
        raise ValueError(f"a polygon needs 3 to {max_vertices} vertices, got {n}")
    padded = jnp.zeros((max_vertices, 2), jnp.float32).at[:n].set(verts)
    centre, local, inverse_mass, inverse_inertia = polygon_mass_properties(
        padded, n, jnp.asarray(density, jnp.float32), mass_convention
    )
    if fixed:
        inverse_mass, inverse_inertia = jnp.zeros_like(inverse_mass), jnp.zeros_like(inverse_inertia)
    # Arena slots are never reused: pairs among them are not enumerated, so shapes there could not collide.
    first = arena_polygon_count(state)
    slot = _free_slot(state.bodies.active[first:num_polygons])
    slot = jnp.where(slot < 0, -1, slot + first)
    world_centre = jnp.asarray(position, jnp.float32) + _rotate_point(rotation, centre)
    bodies = _set_body(
        state.bodies, slot, world_centre, rotation, jnp.asarray(velocity, jnp.float32), angular_velocity,
        inverse_mass, inverse_inertia, friction, restitution, collision_mode,
    )
    at = jnp.where(slot < 0, num_polygons, slot)
    state = state.replace(
        bodies=bodies,
        polygon_vertices=state.polygon_vertices.at[at].set(local, mode="drop"),
        polygon_n_vertices=state.polygon_n_vertices.at[at].set(n, mode="drop"),
    )
    return state, slot


def _rotate_point(angle, point: Array) -> Array:
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * point[0] - s * point[1], s * point[0] + c * point[1]])


def rectangle_vertices(width: float, height: float) -> np.ndarray:
    """Clockwise from the top-left corner, centred on the origin."""
    hw, hh = width / 2.0, height / 2.0
    return np.array([[-hw, hh], [hw, hh], [hw, -hh], [-hw, -hh]], dtype=np.float32)


def add_rectangle(state: SimState, position, width: float, height: float, **kwargs) -> tuple[SimState, Array]:
    return add_polygon(state, position, rectangle_vertices(width, height), **kwargs)


def add_circle(
    state: SimState,
    position,
    radius: float,
    rotation: float = 0.0,
    velocity=(0.0, 0.0),
    angular_velocity: float = 0.0,
    density: float = 1.0,
    friction: float = 1.0,
    restitution: float = 0.0,
    collision_mode: int = 1,
    fixed: bool = False,
    mass_convention: MassConvention = "physical",
) -> tuple[SimState, Array]:
    """Add a disc. Returns (state, body index) where body index = num_polygons + circle slot, or -1 if full."""
    num_polygons = state.polygon_vertices.shape[0]
    inverse_mass, inverse_inertia = circle_mass_properties(
        jnp.asarray(radius, jnp.float32), jnp.asarray(density, jnp.float32), mass_convention
    )
    if fixed:
        inverse_mass, inverse_inertia = jnp.zeros_like(inverse_mass), jnp.zeros_like(inverse_inertia)
    slot = _free_slot(state.bodies.active[num_polygons:])
    index = jnp.where(slot < 0, -1, slot + num_polygons)
    bodies = _set_body(
        state.bodies, index, jnp.asarray(position, jnp.float32), rotation, jnp.asarray(velocity, jnp.float32),
        angular_velocity, inverse_mass, inverse_inertia, friction, restitution, collision_mode,
    )
    at = jnp.where(slot < 0, state.circle_radius.shape[0], slot)
    return state.replace(bodies=bodies, circle_radius=state.circle_radius.at[at].set(radius, mode="drop")), index


def _add_joint(state: SimState, fields: dict) -> tuple[SimState, Array]:
    joints = state.joints
    slot = _free_slot(joints.active)
    at = jnp.where(slot < 0, joints.active.shape[0], slot)
    updates = {
        name: getattr(joints, name).at[at].set(value, mode="drop") for name, value in fields.items()
    }
    updates["active"] = joints.active.at[at].set(True, mode="drop")
    state = state.replace(joints=joints.replace(**updates))
    return refresh_collision_filter(state), slot


def add_revolute_joint(
    state: SimState,
    a_index,
    b_index,
    a_relative_pos,
    b_relative_pos,
    motor_on: bool = False,
    motor_speed: float = 1.0,
    motor_power: float = 1.0,
    has_joint_limits: bool = False,
    min_rotation: float = -np.pi,
    max_rotation: float = np.pi,
    rotation=None,
) -> tuple[SimState, Array]:
    """Pin two bodies together at their anchors, letting them rotate relative to each other.

    `rotation` is the reference relative angle that limits are measured from; by default the current one
    (Jax2D's helper leaves it at 0, so limits silently depend on how the bodies were placed).
    """
    if rotation is None:
        rotation = state.bodies.rotation[b_index] - state.bodies.rotation[a_index]
    return _add_joint(
        state,
        dict(
            a_index=a_index,
            b_index=b_index,
            a_relative_pos=jnp.asarray(a_relative_pos, jnp.float32),
            b_relative_pos=jnp.asarray(b_relative_pos, jnp.float32),
            rotation=rotation,
            is_fixed_joint=False,
            motor_on=motor_on,
            motor_speed=motor_speed,
            motor_power=motor_power,
            motor_has_joint_limits=has_joint_limits,
            min_rotation=min_rotation,
            max_rotation=max_rotation,
            acc_impulse=jnp.zeros(2),
            acc_r_impulse=0.0,
        ),
    )


def add_fixed_joint(
    state: SimState, a_index, b_index, a_relative_pos, b_relative_pos, rotation=None
) -> tuple[SimState, Array]:
    """Weld two bodies; they keep the relative angle `rotation` (by default the current one)."""
    if rotation is None:
        rotation = state.bodies.rotation[b_index] - state.bodies.rotation[a_index]
    return _add_joint(
        state,
        dict(
            a_index=a_index,
            b_index=b_index,
            a_relative_pos=jnp.asarray(a_relative_pos, jnp.float32),
            b_relative_pos=jnp.asarray(b_relative_pos, jnp.float32),
            rotation=rotation,
            is_fixed_joint=True,
            motor_on=False,
            motor_has_joint_limits=False,
            acc_impulse=jnp.zeros(2),
            acc_r_impulse=0.0,
        ),
    )


def add_thruster(
    state: SimState, body_index, relative_position=(0.0, 0.0), rotation: float = 0.0, power: float = 1.0
) -> tuple[SimState, Array]:
    """Attach a thruster to a body; with action 1 it pushes along `rotation` (body frame) at `power` times the
    base thruster power."""
    thrusters = state.thrusters
    slot = _free_slot(thrusters.active)
    at = jnp.where(slot < 0, thrusters.active.shape[0], slot)
    put = lambda arr, value: arr.at[at].set(value, mode="drop")  # noqa: E731
    body = state.bodies
    rel = jnp.asarray(relative_position, jnp.float32)
    angle = body.rotation[body_index]
    world = body.position[body_index] + _rotate_point(angle, rel)
    new = thrusters.replace(
        body_index=put(thrusters.body_index, body_index),
        relative_position=put(thrusters.relative_position, rel),
        rotation=put(thrusters.rotation, rotation),
        power=put(thrusters.power, power),
        active=put(thrusters.active, True),
        global_position=put(thrusters.global_position, world),
    )
    return state.replace(thrusters=new), slot


def connected_by_joints(joints: Joints, num_bodies: int) -> Array:
    """[N, N] bool: bodies linked through any chain of active joints (a body is linked to itself)."""
    body = jnp.arange(num_bodies)
    link = (joints.a_index[:, None] == body) & joints.active[:, None]
    other = (joints.b_index[:, None] == body) & joints.active[:, None]
    adjacency = (link[:, :, None] & other[:, None, :]).any(axis=0)
    reach = adjacency | adjacency.T | jnp.eye(num_bodies, dtype=bool)
    # Repeated squaring: after k rounds, chains of up to 2^k joints are closed.
    for _ in range(max(1, int(np.ceil(np.log2(max(num_bodies, 2)))))):
        reach = (reach[:, :, None] & reach[None, :, :]).any(axis=1)
    return reach


def arena_polygon_count(state: SimState) -> int:
    """Number of arena polygons, recovered from the pair count (arena-arena pairs are not enumerated)."""
    P, C = state.polygon_vertices.shape[0], state.circle_radius.shape[0]
    all_pairs = P * (P - 1) // 2 + P * C + C * (C - 1) // 2
    missing = all_pairs - state.pair_collides.shape[0]
    # missing = S (S - 1) / 2; S = 0 and S = 1 give the same pair tables, so 0 stands for both.
    return int(round((1 + np.sqrt(1 + 8 * missing)) / 2)) if missing else 0


def refresh_collision_filter(state: SimState) -> SimState:
    """Recompute which pairs may exchange contact impulses: bodies connected through joints never collide.

    Called by the joint helpers; call it after editing joints by hand. The step itself never recomputes it.
    """
    num_polygons = state.polygon_vertices.shape[0]
    num_circles = state.circle_radius.shape[0]
    sizes = SceneSizes(
        num_polygons=num_polygons,
        num_circles=num_circles,
        num_joints=state.joints.active.shape[0],
        num_thrusters=state.thrusters.active.shape[0],
        max_polygon_vertices=state.polygon_vertices.shape[1],
        num_static_polygons=arena_polygon_count(state),
    )
    tables = pair_tables(sizes)
    reach = connected_by_joints(state.joints, num_polygons + num_circles)
    return state.replace(pair_collides=~reach[tables.pair_a, tables.pair_b])
