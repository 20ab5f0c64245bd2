"""ACCEL's level edits (Kinetix's `ued/mutators.py` and `make_mutate_env`), on the device.

`mutate_level(key, level, sizes, config)` applies `config.num_edits` edits one after another; each edit picks one
operator with probability proportional to its weight (weights of operators that cannot act, such as adding a
thruster with every thruster slot taken, are zeroed first, as Kinetix does):

| operator | weight | effect |
|---|---|---|
| add_free_shape | 1 | a new unattached rectangle or circle, drawn as by the generator (no proposal filter) |
| add_connected_shape | 1 | a new shape joined to an existing one, as by the generator (no visibility check) |
| remove_joint | 0 | deactivate a random joint |
| remove_shape | 0 | deactivate a random neutral or red shape with its joints and thrusters |
| swap_role | 1 | swap the roles of two shapes with different roles |
| add_thruster | 1 | a thruster on a random dynamic shape, as by the generator |
| remove_thruster | 1 | deactivate a random thruster |
| toggle_fixed | 0.1 | make a random shape fixed, or dynamic with its mass recomputed from its density |
| change_size | 1 | redraw a shape's dimensions; joint anchors and thrusters on it scale along; mass recomputed |
| change_location | 1 | move a shape and everything jointed to it by U(-0.5, 0.5)^2, then back inside the arena |
| change_rotation | 1 | turn a shape by U(0, pi/2); fixed joints on it keep their weld |

After a size or rotation change, `settle_steps` (5) steps with zero gravity, no contacts and zero actions let
the joints pull the scene back together; velocities are zeroed after each and the warm-start caches after all
(as Kinetix's `do_dummy_step`). Every edit leaves a valid level: indices in range, joint collision filter fresh,
the number of green and blue shapes unchanged except by `swap_role` (which keeps the multiset of roles).

Everything is jittable with `sizes` and `config` static and vmaps over levels (`mutate_levels`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.arena import ARENA_METRES
from impulse.engine.levels.draws import DrawLayout
from impulse.engine.levels.generator import (
    SHAPE_ADD_DRAWS,
    SHAPE_DRAWS,
    THRUSTER_DRAWS,
    GeneratorConfig,
    add_shape_from_uniforms,
    add_thruster_from_uniforms,
    choose,
    circle_radius_of,
    local_half_extents,
    refresh_anchor_positions,
    sample_shape,
    uniforms,
)
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, Level, random_level_id
from impulse.engine.physics.building import FLOOR_TOP, connected_by_joints, refresh_collision_filter
from impulse.engine.physics.geometry import rotate
from impulse.engine.physics.mass import circle_mass_properties, polygon_mass_properties
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState
from impulse.engine.physics.step import step

Array = jax.Array

EDIT_NAMES = (
    "add_free_shape",
    "add_connected_shape",
    "remove_joint",
    "remove_shape",
    "swap_role",
    "add_thruster",
    "remove_thruster",
    "toggle_fixed",
    "change_size",
    "change_location",
    "change_rotation",
)
EDIT_INDEX = {name: i for i, name in enumerate(EDIT_NAMES)}



class PickDraws(NamedTuple):
    which: Array  # the slot (shape, joint or thruster) an edit acts on


class SwapDraws(NamedTuple):
    first: Array
    second: Array  # a shape of another role


class ResizeDraws(NamedTuple):
    which: Array
    shape: Array  # [SHAPE_DRAWS.size] new dimensions


class MoveDraws(NamedTuple):
    which: Array
    offset: Array  # [2]


class TurnDraws(NamedTuple):
    which: Array
    turn: Array


PICK_DRAWS = DrawLayout(PickDraws)
SWAP_DRAWS = DrawLayout(SwapDraws)
RESIZE_DRAWS = DrawLayout(ResizeDraws, {"shape": SHAPE_DRAWS.size})
MOVE_DRAWS = DrawLayout(MoveDraws, {"offset": 2})
TURN_DRAWS = DrawLayout(TurnDraws)
EDIT_UNIFORMS = max(layout.size for layout in (SHAPE_ADD_DRAWS, THRUSTER_DRAWS, PICK_DRAWS, SWAP_DRAWS, RESIZE_DRAWS,
                                               MOVE_DRAWS, TURN_DRAWS))
"""Uniform numbers one edit consumes (the largest operator's need); each operator reads its own layout's part."""


class EditDraws(NamedTuple):
    edit: Array  # which edit
    operands: Array  # [EDIT_UNIFORMS] what the edit draws


EDIT_DRAWS = DrawLayout(EditDraws, {"operands": EDIT_UNIFORMS})


@dataclass(frozen=True)
class MutationConfig:
    """ACCEL's mutation settings (Kinetix's `make_mutate_env` weights; `num_edits` 5 as in its accel.yaml).
    Hashable: pass it as a static argument."""

    num_edits: int = 5
    add_free_shape_weight: float = 1.0
    add_connected_shape_weight: float = 1.0
    remove_joint_weight: float = 0.0
    remove_shape_weight: float = 0.0
    swap_role_weight: float = 1.0
    add_thruster_weight: float = 1.0
    remove_thruster_weight: float = 1.0
    toggle_fixed_weight: float = 0.1
    change_size_weight: float = 1.0
    change_location_weight: float = 1.0
    change_rotation_weight: float = 1.0
    max_location_offset: float = 0.5  # metres per axis
    max_rotation_change: float = math.pi / 2.0
    settle_steps: int = 5  # after change_size and change_rotation; 0 skips settling
    shapes: GeneratorConfig = GeneratorConfig()  # how new shapes, joints and thrusters are drawn

    @property
    def weights(self) -> tuple[float, ...]:
        """Operator weights in EDIT_NAMES order."""
        return tuple(getattr(self, f"{name}_weight") for name in EDIT_NAMES)


# ---------------------------------------------------------------------------------------------------------------
# Helpers


def _shape_candidates(level: Level, sizes: SceneSizes) -> Array:
    """[N] active non-arena shapes."""
    active = level.state.bodies.active
    return active & (jnp.arange(active.shape[0]) >= sizes.num_static_polygons)


def _mask(mask: Array, like: Array) -> Array:
    return mask.reshape(mask.shape + (1,) * (like.ndim - 1))


def mass_from_density(state: SimState, densities: Array, body: Array, sizes: SceneSizes) -> tuple[Array, Array]:
    """(inverse mass, inverse inertia) of `body` from its geometry and density, in Jax2D's convention."""
    P = sizes.num_polygons
    poly = jnp.minimum(body, P - 1)
    density = densities[body]
    _, _, poly_im, poly_ii = polygon_mass_properties(
        state.polygon_vertices[poly], state.polygon_n_vertices[poly], density, "jax2d"
    )
    circle_im, circle_ii = circle_mass_properties(circle_radius_of(state, body, sizes), density, "jax2d")
    is_polygon = body < P
    return jnp.where(is_polygon, poly_im, circle_im), jnp.where(is_polygon, poly_ii, circle_ii)


def _set_body_mass(level: Level, hot: Array, inverse_mass: Array, inverse_inertia: Array) -> Level:
    bodies = level.state.bodies
    bodies = bodies.replace(
        inverse_mass=jnp.where(hot, inverse_mass, bodies.inverse_mass),
        inverse_inertia=jnp.where(hot, inverse_inertia, bodies.inverse_inertia),
        velocity=jnp.where(hot[:, None], 0.0, bodies.velocity),
        angular_velocity=jnp.where(hot, 0.0, bodies.angular_velocity),
    )
    return level.replace(state=level.state.replace(bodies=bodies))


def _body_extents(state: SimState, sizes: SceneSizes) -> tuple[Array, Array]:
    """[N, 2] lowest and highest world offsets of each body's outline from its position."""
    P, V = sizes.num_polygons, sizes.max_polygon_vertices
    bodies = state.bodies
    world = rotate(bodies.rotation[:P, None], state.polygon_vertices)  # [P, V, 2]
    valid = (jnp.arange(V)[None, :] < state.polygon_n_vertices[:, None])[..., None]
    poly_low = jnp.where(valid, world, jnp.inf).min(axis=1)
    poly_high = jnp.where(valid, world, -jnp.inf).max(axis=1)
    radius = state.circle_radius[:, None]
    return jnp.concatenate([poly_low, -jnp.broadcast_to(radius, (sizes.num_circles, 2))]), jnp.concatenate(
        [poly_high, jnp.broadcast_to(radius, (sizes.num_circles, 2))]
    )


def settle(level: Level, sizes: SceneSizes, steps: int) -> Level:
    """Kinetix's settling after a size or rotation change: `steps` engine steps with zero gravity, contacts off
    and zero actions, velocities zeroed after each; warm-start caches cleared at the end. The steps use the default
    solver options, so an edited level does not depend on how the trainer that asked for it solves its scenes."""
    state = level.state
    quiet = state.replace(gravity=jnp.zeros_like(state.gravity), pair_collides=jnp.zeros_like(state.pair_collides))
    actions = jnp.zeros((sizes.num_joints + sizes.num_thrusters,), jnp.float32)
    params = SimParams()

    def one_step(_, s: SimState) -> SimState:
        s, _ = step(s, params, actions, sizes)
        b = s.bodies
        return s.replace(
            bodies=b.replace(velocity=jnp.zeros_like(b.velocity), angular_velocity=jnp.zeros_like(b.angular_velocity))
        )

    settled = jax.lax.fori_loop(0, steps, one_step, quiet)
    joints, contacts = settled.joints, settled.contacts
    settled = settled.replace(
        gravity=state.gravity,
        pair_collides=state.pair_collides,
        joints=joints.replace(
            acc_impulse=jnp.zeros_like(joints.acc_impulse), acc_r_impulse=jnp.zeros_like(joints.acc_r_impulse)
        ),
        contacts=jax.tree.map(jnp.zeros_like, contacts),
    )
    return level.replace(state=settled)


# ---------------------------------------------------------------------------------------------------------------
# Operators: (uniforms [EDIT_UNIFORMS], level) -> (level, whether to settle). None refreshes the collision filter;
# `apply_edit` does that once after any of them. The two shape additions are in `_apply`.


def _deactivate_one(u: Array, active: Array) -> Array:
    """`active` with one of its active slots (chosen by the uniform `u`) switched off; unchanged if none is."""
    slot, any_active = choose(u, active)
    return active & ~((jnp.arange(active.shape[0]) == slot) & any_active)


def _remove_joint(u, level, sizes, config):
    joints = level.state.joints.replace(active=_deactivate_one(PICK_DRAWS.split(u).which, level.state.joints.active))
    return level.replace(state=level.state.replace(joints=joints)), jnp.asarray(False)


def _remove_shape(u, level, sizes, config):
    # Never the green or blue shape: a level without them could not be solved (Kinetix does not guard this).
    candidates = _shape_candidates(level, sizes) & (level.roles != ROLE_GREEN) & (level.roles != ROLE_BLUE)
    body, any_body = choose(PICK_DRAWS.split(u).which, candidates)
    state = level.state
    hot = (jnp.arange(sizes.num_bodies) == body) & any_body
    joints, thrusters = state.joints, state.thrusters
    joint_hit = ((joints.a_index == body) | (joints.b_index == body)) & any_body
    state = state.replace(
        bodies=state.bodies.replace(active=state.bodies.active & ~hot),
        joints=joints.replace(active=joints.active & ~joint_hit),
        thrusters=thrusters.replace(active=thrusters.active & ~((thrusters.body_index == body) & any_body)),
    )
    return level.replace(state=state), jnp.asarray(False)


def _swap_role(u, level, sizes, config):
    candidates = _shape_candidates(level, sizes)
    roles = level.roles
    present = ((jax.nn.one_hot(roles, 4) * candidates[:, None]).sum(axis=0) > 0).sum()
    draws = SWAP_DRAWS.split(u)
    first, _ = choose(draws.first, candidates)
    second, any_other = choose(draws.second, candidates & (roles != roles[first]))
    do = (present >= 2) & any_other
    body = jnp.arange(sizes.num_bodies)
    swapped = jnp.where(body == first, roles[second], jnp.where(body == second, roles[first], roles))
    return level.replace(roles=jnp.where(do, swapped, roles)), jnp.asarray(False)


def _add_thruster(u, level, sizes, config):
    return add_thruster_from_uniforms(u[: THRUSTER_DRAWS.size], level, sizes, config.shapes), jnp.asarray(False)


def _remove_thruster(u, level, sizes, config):
    which = PICK_DRAWS.split(u).which
    thrusters = level.state.thrusters.replace(active=_deactivate_one(which, level.state.thrusters.active))
    return level.replace(state=level.state.replace(thrusters=thrusters)), jnp.asarray(False)


def _toggle_fixed(u, level, sizes, config):
    body, any_body = choose(PICK_DRAWS.split(u).which, _shape_candidates(level, sizes))
    hot = (jnp.arange(sizes.num_bodies) == body) & any_body
    was_fixed = level.state.bodies.inverse_mass[body] == 0
    inverse_mass, inverse_inertia = mass_from_density(level.state, level.densities, body, sizes)
    level = _set_body_mass(
        level, hot, jnp.where(was_fixed, inverse_mass, 0.0), jnp.where(was_fixed, inverse_inertia, 0.0)
    )
    return level, jnp.asarray(False)


def _change_size(u, level, sizes, config):
    P, N = sizes.num_polygons, sizes.num_bodies
    draws = RESIZE_DRAWS.split(u)
    body, any_body = choose(draws.which, _shape_candidates(level, sizes))
    state = level.state
    is_rect = body < P
    shape = sample_shape(draws.shape, is_rect, config.shapes.max_shape_size, config.shapes,
                         sizes.max_polygon_vertices)
    poly = jnp.minimum(body, P - 1)
    # Per-axis ratio of the new to the old local half-size: for Kinetix's centred rectangles this is its ratio of
    # the (-hx, -hy) corners; for other polygons it keeps the winding (Kinetix's corner ratio can flip it).
    old_half = local_half_extents(state.polygon_vertices[poly], state.polygon_n_vertices[poly])
    circle_scale = shape.radius / circle_radius_of(state, body, sizes)
    scale = jnp.where(is_rect, shape.half / old_half, jnp.stack([circle_scale, circle_scale]))
    poly_hot = (jnp.arange(P) == body) & any_body
    circle_hot = (P + jnp.arange(sizes.num_circles) == body) & any_body
    joints, thrusters = state.joints, state.thrusters
    on_a = ((joints.a_index == body) & any_body)[:, None]
    on_b = ((joints.b_index == body) & any_body)[:, None]
    on_thruster = ((thrusters.body_index == body) & any_body)[:, None]
    state = state.replace(
        polygon_vertices=jnp.where(poly_hot[:, None, None], state.polygon_vertices * scale, state.polygon_vertices),
        circle_radius=jnp.where(circle_hot, shape.radius, state.circle_radius),
        joints=joints.replace(
            a_relative_pos=jnp.where(on_a, joints.a_relative_pos * scale, joints.a_relative_pos),
            b_relative_pos=jnp.where(on_b, joints.b_relative_pos * scale, joints.b_relative_pos),
        ),
        thrusters=thrusters.replace(
            relative_position=jnp.where(on_thruster, thrusters.relative_position * scale, thrusters.relative_position)
        ),
    )
    level = level.replace(state=state)
    hot = (jnp.arange(N) == body) & any_body & (state.bodies.inverse_mass != 0)
    inverse_mass, inverse_inertia = mass_from_density(state, level.densities, body, sizes)
    return _set_body_mass(level, hot, inverse_mass, inverse_inertia), any_body


def _change_location(u, level, sizes, config):
    N = sizes.num_bodies
    candidates = _shape_candidates(level, sizes)
    draws = MOVE_DRAWS.split(u)
    body, any_body = choose(draws.which, candidates)
    state = level.state
    bodies = state.bodies
    offset = (2.0 * draws.offset - 1.0) * config.max_location_offset
    group = connected_by_joints(state.joints, N)[body] & candidates & any_body
    position = bodies.position + jnp.where(group[:, None], offset, 0.0)
    # Shift the moved group back inside x in [0, 5], y in [FLOOR_TOP, 5] by its world bounding box.
    low_offset, high_offset = _body_extents(state, sizes)
    low = jnp.where(group[:, None], position + low_offset, jnp.inf).min(axis=0)
    high = jnp.where(group[:, None], position + high_offset, -jnp.inf).max(axis=0)
    floor = jnp.asarray([0.0, FLOOR_TOP], jnp.float32)
    shift = jnp.maximum(0.0, floor - low) - jnp.maximum(0.0, high - ARENA_METRES)
    shift = jnp.where(jnp.isfinite(shift), shift, 0.0)
    position = position + jnp.where(group[:, None], shift, 0.0)
    return level.replace(state=state.replace(bodies=bodies.replace(position=position))), jnp.asarray(False)


def _change_rotation(u, level, sizes, config):
    draws = TURN_DRAWS.split(u)
    body, any_body = choose(draws.which, _shape_candidates(level, sizes))
    state = level.state
    bodies, joints = state.bodies, state.joints
    delta = jnp.where(any_body, draws.turn * config.max_rotation_change, 0.0)
    hot = jnp.arange(sizes.num_bodies) == body
    welded = joints.active & joints.is_fixed_joint
    # A fixed joint holds rotation_b - rotation_a at its reference: move the reference with the turned shape.
    reference = joints.rotation - jnp.where(welded & (joints.a_index == body), delta, 0.0)
    reference = reference + jnp.where(welded & (joints.b_index == body), delta, 0.0)
    state = state.replace(
        bodies=bodies.replace(rotation=bodies.rotation + jnp.where(hot, delta, 0.0)),
        joints=joints.replace(rotation=reference),
    )
    return level.replace(state=state), any_body


_OPERATORS = (
    None,  # add_free_shape and add_connected_shape: one shared branch in `_apply`
    None,
    _remove_joint,
    _remove_shape,
    _swap_role,
    _add_thruster,
    _remove_thruster,
    _toggle_fixed,
    _change_size,
    _change_location,
    _change_rotation,
)
assert len(_OPERATORS) == len(EDIT_NAMES)


# ---------------------------------------------------------------------------------------------------------------
# Edits


def _apply(u: Array, level: Level, sizes: SceneSizes, edit: Array, config: MutationConfig) -> Level:
    # The two shape additions share one branch (they differ only in a flag), which keeps the program smaller.
    connected = edit == EDIT_INDEX["add_connected_shape"]

    def add_shape(u, level):
        level, _ = add_shape_from_uniforms(u[: SHAPE_ADD_DRAWS.size], level, sizes, config.shapes, connected, False,
                                           False)
        return level, jnp.asarray(False)

    branches = [add_shape] + [functools.partial(op, sizes=sizes, config=config) for op in _OPERATORS[2:]]
    branch = jnp.maximum(edit - 1, 0)  # edits 0 and 1 -> branch 0, edit k >= 2 -> branch k - 1
    level, needs_settling = jax.lax.switch(branch, branches, u, level)
    if config.settle_steps > 0:
        level = jax.lax.cond(
            needs_settling, lambda lv: settle(lv, sizes, config.settle_steps), lambda lv: lv, level
        )
    state = refresh_anchor_positions(refresh_collision_filter(level.state))
    return level.replace(state=state)


def edit_weights(level: Level, sizes: SceneSizes, config: MutationConfig) -> Array:
    """[len(EDIT_NAMES)] the operators' weights on this level: the configured ones, zeroed where Kinetix zeroes
    them (no free shape slot, no free joint slot, no free thruster slot, no thruster)."""
    S = sizes.num_static_polygons
    state = level.state
    active = state.bodies.active
    shape_room = (~active[S:]).any() if sizes.num_bodies > S else jnp.asarray(False)
    joint_room = (~state.joints.active).any() if sizes.num_joints else jnp.asarray(False)
    thruster_room = (~state.thrusters.active).any() if sizes.num_thrusters else jnp.asarray(False)
    any_thruster = state.thrusters.active.any() if sizes.num_thrusters else jnp.asarray(False)
    gate = jnp.stack([
        shape_room,
        shape_room & joint_room,
        jnp.asarray(True),
        jnp.asarray(True),
        jnp.asarray(True),
        thruster_room,
        any_thruster,
        jnp.asarray(True),
        jnp.asarray(True),
        jnp.asarray(True),
        jnp.asarray(True),
    ])
    return jnp.asarray(config.weights, jnp.float32) * gate


def apply_edit(
    key: Array, level: Level, sizes: SceneSizes, edit, config: MutationConfig = MutationConfig()
) -> Level:
    """Apply one operator (an index into EDIT_NAMES, or its name) to `level`. Jittable; `edit` may be traced."""
    if isinstance(edit, str):
        edit = EDIT_INDEX[edit]
    return _apply(uniforms(key, (EDIT_UNIFORMS,)), level, sizes, jnp.asarray(edit, jnp.int32), config)

CHILD_ID_STREAM = 0x2D
"""`fold_in` tag that derives a mutated child's id from the mutation key."""


def mutate_level(
    key: Array,
    level: Level,
    sizes: SceneSizes,
    config: MutationConfig = MutationConfig(),
    num_edits: Array | None = None,
) -> Level:
    """`config.num_edits` random edits in a row (ACCEL's mutation). Pure; jit with `sizes` and `config` static.
    The child is a new level, with a new id drawn from `key`. A traced `num_edits` (at most `config.num_edits`)
    applies only that many of the edits, so a curriculum can change the count without recompiling."""
    child_id = random_level_id(jax.random.fold_in(key, CHILD_ID_STREAM))
    if config.num_edits == 0:
        return level.replace(level_id=child_id)
    draws = EDIT_DRAWS.split(uniforms(key, (config.num_edits, EDIT_DRAWS.size)))
    wanted = config.num_edits if num_edits is None else num_edits

    def one_edit(level: Level, indexed: tuple[Array, EditDraws]) -> tuple[Level, Array]:
        index, edit_draws = indexed
        edit, _ = choose(edit_draws.edit, edit_weights(level, sizes, config))
        edited = _apply(edit_draws.operands, level, sizes, edit, config)
        keep = index < wanted
        return jax.tree.map(lambda new, old: jnp.where(keep, new, old), edited, level), edit

    level, _ = jax.lax.scan(one_edit, level, (jnp.arange(config.num_edits), draws))
    return level.replace(level_id=child_id)


@functools.partial(jax.jit, static_argnames=("sizes", "config"))
def mutate_levels(key: Array, levels: Level, sizes: SceneSizes, config: MutationConfig = MutationConfig()) -> Level:
    """`mutate_level` over a batch of levels (leading axis), each with its own key, jitted."""
    keys = jax.random.split(key, levels.roles.shape[0])
    return jax.vmap(lambda k, lv: mutate_level(k, lv, sizes, config))(keys, levels)
