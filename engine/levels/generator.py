"""Random levels in the style of Kinetix's level generator, sampled on the device.

`sample_random_level(key, sizes, config)` builds one level from a key; it is pure and jittable with `sizes` and
`config` static, so `jax.vmap` over keys samples a batch (see `sample_random_levels`). The procedure and its
distributions follow Kinetix's `sample_kinetix_level` (UED parameters in `GeneratorConfig`):

1. the empty arena; the floor gets a role (neutral 0.9, green 0, blue 0.02, red 0.08);
2. two free shapes, which become the green and the blue one (a blue floor takes the blue role); a coin decides
   which of the two may not be fixed, so they are never both fixed;
3. forced controls, uniformly one of motor only / thruster only / both: a motor is a new shape linked by a
   revolute joint (otherwise a free shape is added instead); a thruster goes on a dynamic shape;
4. each remaining shape slot (P + C - 7 of them): connected shape 0.35, free shape 0.35, nothing 0.3;
5. T - 1 extra thrusters, each with probability 0.3;
6. with a neutral floor, green and blue swap roles with probability 0.5 (removes the left/right bias of step 2);
7. the non-arena polygons, the circles, the joints and the thrusters are put in random slot order.

Free and connected shapes are chosen among K placement proposals (8; 1 in scenes of at most 7 shapes, which
also never fix shapes): the proposal whose scene has the fewest touching contact points wins, a connected shape
whose two shapes cannot both be seen around their joint counting 10 more.

The whole level is built by one `lax.scan` over a fixed list of attempts (add a free shape, a connected shape,
a thruster, or nothing), writing bodies, shapes, joints and thrusters through the scene builder's slot writers
(`engine.physics.building`, one-hot selects), so the compiled program stays small for every size (Kinetix's
large-size generator took minutes to compile) and a slot is filled as the scene builder fills it.

`add_free_shape`, `add_connected_shape` and `add_thruster` are the single-attempt building blocks, also used
by the ACCEL mutations (`engine.levels.mutations`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.arena import ARENA_METRES
from impulse.engine.levels.draws import DrawLayout
from impulse.engine.levels.level import (
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    ROLE_BLUE,
    ROLE_GREEN,
    ROLE_NEUTRAL,
    ROLE_RED,
    Level,
    level_from_scene,
    random_level_id,
)
from impulse.engine.physics.building import (
    FLOOR_TOP,
    empty_scene,
    put_rows,
    refresh_collision_filter,
    write_body,
    write_circle,
    write_joint,
    write_polygon,
    write_thruster,
)
from impulse.engine.physics.geometry import rotate
from impulse.engine.physics.mass import circle_mass_properties, polygon_mass_properties
from impulse.engine.physics.narrowphase import detect_contacts
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import Joints, SimState

Array = jax.Array

_SQRT2 = math.sqrt(2.0)
_TWO_PI = 2.0 * math.pi

# Attempt kinds of the generator's scan.
_NOTHING, _FREE_SHAPE, _CONNECTED_SHAPE, _THRUSTER = 0, 1, 2, 3


@dataclass(frozen=True)
class GeneratorConfig:
    """Kinetix's `UEDParams` defaults, under descriptive names (Kinetix's name in brackets where it differs).

    Hashable: pass it as a static argument. Constants Kinetix hard-codes are fields here too, with its values.
    """

    # Shape dimensions. Rectangle half-extents are U(min_half_extent, max_shape_size / (2 sqrt 2)) per axis, one
    # axis stretched by large_dimension_scale with large_dimension_chance; circle radii are
    # U(min_radius, max_shape_size / 2 * circle_max_size_coeff).
    max_shape_size: float = 1.0
    goal_size_factor: float = 1.0  # [goal_body_size_factor] size multiplier of free green/blue shapes
    large_dimension_chance: float = 0.3  # [large_rect_dim_chance]
    large_dimension_scale: float = 2.0  # [large_rect_dim_scale]
    circle_max_size_coeff: float = 0.8
    min_half_extent: float = 0.05  # hard-coded in Kinetix
    min_radius: float = 0.1  # hard-coded in Kinetix
    density: float = 1.0  # hard-coded in Kinetix
    # Free-shape placement: green in the left half and blue in the right half with this chance.
    opposite_side_chance: float = 0.5  # [goal_body_opposide_side_chance]
    # Fixation of free shapes: p = min(fixate_chance_min + fixate_chance_scale * mass, fixate_chance_max); a fixed
    # shape in the upper half moves down by half the arena with the bottom bias (more for green/blue/red shapes).
    fixate_chance_min: float = 0.02
    fixate_chance_max: float = 1.0
    fixate_chance_scale: float = 4.0
    fixate_bottom_bias: float = 0.0  # [fixate_shape_bottom_bias]
    fixate_bottom_bias_special_role: float = 0.6  # [fixate_shape_bottom_bias_special_role]
    # Connected shapes.
    revolute_chance: float = 0.5  # hard-coded in Kinetix (its joint_fixed_chance is unused)
    min_revolute_joints: int = 2  # [min_rjoints_bias] joints are revolute while fewer than this exist
    connect_to_fixed_weight: float = 0.05  # [connect_to_fixated_prob_coeff] target weight of a fixed shape
    visibility_margin: float = 0.05  # [connect_visibility_min]
    no_visibility_penalty: float = 10.0  # [connect_no_visibility_bias] added to a hidden proposal's score
    motor_on_chance: float = 0.8
    motor_min_speed: float = 0.4
    motor_max_speed: float = 3.0
    motor_min_power: float = 1.0
    motor_max_power: float = 3.0  # rectangle-rectangle joints
    wheel_max_power: float = 1.0  # joints with a circle ("high-powered wheels break the engine")
    joint_limit_chance: float = 0.4  # rectangle-rectangle revolute joints only
    joint_limit_max: float = math.pi
    # Thrusters: power = mass * thruster_power_multiplier * U(thruster_min_factor, thruster_max_factor).
    thruster_power_multiplier: float = 2.0
    thruster_min_factor: float = 0.5  # hard-coded in Kinetix
    thruster_max_factor: float = 2.0  # hard-coded in Kinetix
    thruster_align_com_chance: float = 0.8  # [thruster_align_com_prob] aim through the centre of mass
    # Composition of the level.
    add_connected_shape_chance: float = 0.35
    add_free_shape_chance: float = 0.35  # [add_shape_chance]
    add_nothing_chance: float = 0.3  # [add_no_shape_chance]
    add_thruster_chance: float = 0.3
    num_proposals: int = 8  # [add_shape_n_proposals]
    small_scene_max_shapes: int = 7  # P + C at most this: 1 proposal, no fixation (Kinetix's S rule)
    red_weight: float = 1.0 / 3.0  # weight of red against neutral (1) while the level has no red shape
    floor_role_probs: tuple[float, float, float, float] = (0.9, 0.0, 0.02, 0.08)  # neutral, green, blue, red
    swap_green_blue_chance: float = 0.5
    permute_slots: bool = True  # Kinetix's final random slot order


# ---------------------------------------------------------------------------------------------------------------
# Small helpers


def uniforms(key: Array, shape) -> Array:
    """All the uniform [0, 1) numbers an operation needs, from one draw: every separate `jax.random` call adds a
    threefry hash to the program, and dozens of them cost seconds of compile time."""
    return jax.random.uniform(key, shape, jnp.float32)


def _between(u: Array, low, high) -> Array:
    return low + u * (high - low)


def choose(u: Array, weights) -> tuple[Array, Array]:
    """An index drawn with probability proportional to `weights` (>= 0) from a uniform `u` in [0, 1), and whether
    any weight was positive (if none was, the index is meaningless). Zero-weight entries are never drawn."""
    weights = jnp.asarray(weights, jnp.float32)
    cumulative = jnp.cumsum(weights)
    total = cumulative[-1]
    threshold = total * (1.0 - u)  # in (0, total]
    index = jnp.sum(cumulative < threshold).astype(jnp.int32)
    return jnp.minimum(index, weights.shape[0] - 1), total > 0


def first_free(active: Array, start: int = 0) -> tuple[Array, Array]:
    """(first slot at or after `start` that is not active, whether there is one)."""
    if active.shape[0] <= start:
        return jnp.asarray(0, jnp.int32), jnp.asarray(False)
    tail = active[start:]
    slot = jnp.argmin(tail).astype(jnp.int32)
    return slot + start, ~tail[slot]


def _non_arena(sizes: SceneSizes) -> Array:
    return jnp.arange(sizes.num_bodies) >= sizes.num_static_polygons


def role_counts(level: Level) -> Array:
    """[4] number of active bodies of each role, the arena (hence the floor) included."""
    active = level.state.bodies.active
    return (jax.nn.one_hot(level.roles, 4, dtype=jnp.int32) * active[:, None]).sum(axis=0)


def joint_counts(level: Level) -> Array:
    """[N] number of active joints on each body."""
    joints = level.state.joints
    body = jnp.arange(level.roles.shape[0])
    on = joints.active[:, None]
    return (((joints.a_index[:, None] == body) & on).sum(0) + ((joints.b_index[:, None] == body) & on).sum(0)).astype(
        jnp.int32
    )


def circle_radius_of(state: SimState, body: Array, sizes: SceneSizes) -> Array:
    """The radius of `body` if it is a circle (meaningless otherwise; 0 in scenes without circles)."""
    if sizes.num_circles == 0:
        return jnp.asarray(0.0, jnp.float32)
    return state.circle_radius[jnp.clip(body - sizes.num_polygons, 0, sizes.num_circles - 1)]


def _rectangle_vertices(half: Array, max_vertices: int) -> Array:
    """Kinetix's rectangle: clockwise from the top-right corner, centred; padded with zeros to max_vertices."""
    signs = jnp.asarray([[1.0, 1.0], [1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0]], jnp.float32)
    return jnp.zeros((max_vertices, 2), jnp.float32).at[:4].set(signs * half)


def local_half_extents(vertices: Array, n_vertices: Array) -> Array:
    """[2] half-size of a polygon's axis-aligned box in its own frame."""
    valid = (jnp.arange(vertices.shape[0]) < n_vertices)[:, None]
    high = jnp.where(valid, vertices, -jnp.inf).max(axis=0)
    low = jnp.where(valid, vertices, jnp.inf).min(axis=0)
    return (high - low) / 2.0


def _random_point_in_polygon(u: Array, vertices: Array, n_vertices: Array) -> Array:
    """Kinetix's rule, from two uniforms: uniform in a triangle; uniform in the local axis-aligned box of a larger
    polygon."""
    f1, f2 = u[0], u[1]
    v0, v1, v2 = vertices[0], vertices[1], vertices[2]
    in_triangle = v0 + jnp.sqrt(f1) * (v1 - v0 + f2 * (v2 - v1))
    valid = (jnp.arange(vertices.shape[0]) < n_vertices)[:, None]
    high = jnp.where(valid, vertices, -jnp.inf).max(axis=0)
    low = jnp.where(valid, vertices, jnp.inf).min(axis=0)
    in_box = low + jnp.stack([f1, f2]) * (high - low)
    return jnp.where(n_vertices <= 3, in_triangle, in_box)


class SampledShape(NamedTuple):
    half: Array  # [2] rectangle half-extents (Kinetix's values are drawn for circles too; used for the margin)
    radius: Array  # circle radius (min_radius for rectangles, as in Kinetix)
    vertices: Array  # [V, 2] rectangle vertices
    inverse_mass: Array  # of the chosen kind at config.density
    inverse_inertia: Array


class ShapeDraws(NamedTuple):
    half_extents: Array  # [2] rectangle half-size, as a fraction of the allowed range
    long_axis: Array  # which axis a large dimension stretches
    large_dimension: Array  # whether it does
    radius: Array  # circle radius, as a fraction of the allowed range


SHAPE_DRAWS = DrawLayout(ShapeDraws, {"half_extents": 2})


def sample_shape(u: Array, is_rect: Array, max_size: Array, config: GeneratorConfig, max_vertices: int):
    """Dimensions of a new rectangle or circle (Kinetix's `sample_dimensions`) from SHAPE_DRAWS.size uniforms, and
    its mass properties in Jax2D's convention (what Kinetix levels carry)."""
    draws = SHAPE_DRAWS.split(u)
    cap_half = max_size / (2.0 * _SQRT2)
    cap_radius = max_size / 2.0 * config.circle_max_size_coeff
    half = jnp.where(is_rect, draws.half_extents, 0.0) * (cap_half - config.min_half_extent) + config.min_half_extent
    long_axis = jnp.floor(draws.long_axis * 2.0)
    stretch = jnp.where(draws.large_dimension < config.large_dimension_chance, config.large_dimension_scale, 1.0)
    half = half * jnp.where(jnp.arange(2) == long_axis, stretch, 1.0)
    radius = jnp.where(is_rect, 0.0, draws.radius) * (cap_radius - config.min_radius) + config.min_radius
    vertices = _rectangle_vertices(half, max_vertices)
    density = jnp.asarray(config.density, jnp.float32)
    _, _, poly_im, poly_ii = polygon_mass_properties(vertices, 4, density, "jax2d")
    circle_im, circle_ii = circle_mass_properties(radius, density, "jax2d")
    return SampledShape(
        half=half,
        radius=radius,
        vertices=vertices,
        inverse_mass=jnp.where(is_rect, poly_im, circle_im),
        inverse_inertia=jnp.where(is_rect, poly_ii, circle_ii),
    )


def _draw_role(u: Array, level: Level, allowed: Array, config: GeneratorConfig) -> Array:
    """Kinetix's role rule: green and blue first (uniform between the missing ones, the floor counting); then
    neutral (weight 1) or red (red_weight, only while there is no red shape). `allowed` masks roles out."""
    counts = role_counts(level)
    needs_green, needs_blue, needs_red = counts[ROLE_GREEN] == 0, counts[ROLE_BLUE] == 0, counts[ROLE_RED] == 0
    both = ~needs_green & ~needs_blue
    weights = jnp.stack([both, needs_green, needs_blue, both & needs_red]).astype(jnp.float32)
    weights = weights * jnp.asarray([1.0, 1.0, 1.0, config.red_weight], jnp.float32) * allowed
    role, any_allowed = choose(u, weights)
    return jnp.where(any_allowed, role, ROLE_NEUTRAL)


def _allowed_roles_next_to(target_role: Array) -> Array:
    """[4] roles a shape joined to a `target_role` shape may take: no green-blue links, nothing special on red."""
    role = jnp.arange(4)
    special = (target_role == ROLE_GREEN) | (target_role == ROLE_BLUE)
    allowed = jnp.where(special, (role != 3 - target_role) & (role != ROLE_RED), True)
    allowed = jnp.where(target_role == ROLE_RED, (role != ROLE_GREEN) & (role != ROLE_BLUE), allowed)
    return allowed.astype(jnp.float32)


def _box_inner_distance(half: Array, point: Array) -> Array:
    """Distance from a point inside a box to the box's nearest side."""
    return jnp.minimum(half[0] - jnp.abs(point[0]), half[1] - jnp.abs(point[1]))


def _box_outer_distance(half: Array, point: Array) -> Array:
    """Distance from a point to the box's farthest corner."""
    dx = jnp.maximum(jnp.abs(half[0] - point[0]), jnp.abs(-half[0] - point[0]))
    dy = jnp.maximum(jnp.abs(half[1] - point[1]), jnp.abs(-half[1] - point[1]))
    return jnp.sqrt(dx * dx + dy * dy)


def _sticks_out(margin, rect_a, half_a, radius_a, anchor_a, rect_b, half_b, radius_b, anchor_b) -> Array:
    """Whether shape a, pinned at anchor_a to b's anchor_b, can be seen beyond b (Kinetix's visibility test)."""
    reach_a = _box_outer_distance(half_a, anchor_a)
    cover_b = _box_inner_distance(half_b, anchor_b)
    return jnp.where(
        rect_a,
        jnp.where(rect_b, reach_a > cover_b + margin, reach_a > radius_b + margin),
        jnp.where(rect_b, cover_b + margin < radius_a, False),
    )


def refresh_anchor_positions(state: SimState) -> SimState:
    """Recompute joints' and thrusters' world positions from the bodies (what a step would write)."""
    bodies, joints, thrusters = state.bodies, state.joints, state.thrusters
    a = joints.a_index
    joint_world = bodies.position[a] + rotate(bodies.rotation[a], joints.a_relative_pos)
    t = thrusters.body_index
    thruster_world = bodies.position[t] + rotate(bodies.rotation[t], thrusters.relative_position)
    return state.replace(
        joints=joints.replace(global_position=joint_world),
        thrusters=thrusters.replace(global_position=thruster_world),
    )


# ---------------------------------------------------------------------------------------------------------------
# Single attempts


class ShapeAddDraws(NamedTuple):
    target_kind: Array  # joined to a rectangle or a circle
    target: Array  # which one
    kind: Array  # the new shape: rectangle or circle
    role: Array
    rotation: Array
    opposite_side: Array  # green left / blue right
    free_position: Array  # [2]
    fixate: Array
    fixate_at_bottom: Array
    new_anchor: Array  # [2] joint anchor on the new rectangle
    target_anchor: Array  # [2] joint anchor on the target rectangle
    revolute: Array
    motor_on: Array
    motor_speed: Array
    motor_power: Array
    wheel_power: Array
    joint_limits: Array
    min_rotation: Array
    max_rotation: Array
    motor_binding: Array
    shape: Array  # [SHAPE_DRAWS.size] the new shape's dimensions


SHAPE_ADD_DRAWS = DrawLayout(ShapeAddDraws, {"free_position": 2, "new_anchor": 2, "target_anchor": 2,
                                             "shape": SHAPE_DRAWS.size})


class _FreeSlots(NamedTuple):
    """Where a new shape and its joint would go: the first free slot of each kind, and whether there is one."""

    polygon: Array  # body index
    polygon_free: Array
    circle: Array  # body index
    circle_free: Array
    joint: Array
    joint_free: Array


def _free_slots(level: Level, sizes: SceneSizes) -> _FreeSlots:
    """The first free non-arena polygon, circle and joint slots of `level`."""
    P, S = sizes.num_polygons, sizes.num_static_polygons
    active = level.state.bodies.active
    polygon, polygon_free = first_free(active[:P], start=S)
    circle, circle_free = first_free(active[P:])
    joint, joint_free = first_free(level.state.joints.active)
    return _FreeSlots(polygon, polygon_free, circle + P, circle_free, joint, joint_free)


class _Target(NamedTuple):
    """The existing shape a connected shape joins."""

    index: Array  # body index (meaningless when `exists` is false)
    is_rect: Array
    exists: Array


def _choose_target(draws: ShapeAddDraws, level: Level, sizes: SceneSizes, config: GeneratorConfig,
                   polygon_free: Array) -> _Target:
    """Kinetix's target rule: active non-arena shapes, fixed ones rarely, rectangles with fewer than two joints
    and circles with none; a circle target needs room for a new rectangle (no circle-circle links)."""
    bodies = level.state.bodies
    is_polygon_slot = jnp.arange(sizes.num_bodies) < sizes.num_polygons
    links = joint_counts(level)
    weight = (bodies.active & _non_arena(sizes)).astype(jnp.float32)
    weight = weight * jnp.where(bodies.inverse_mass == 0, config.connect_to_fixed_weight, 1.0)
    weight = weight * jnp.where(is_polygon_slot, jnp.maximum(2.0 - links, 0.0) / 2.0, (links == 0) * 1.0)
    rect_weight = jnp.where(is_polygon_slot, weight, 0.0)
    circle_weight = jnp.where(is_polygon_slot, 0.0, weight)
    target_kinds = jnp.stack([rect_weight.sum() > 0, (circle_weight.sum() > 0) & polygon_free])
    target_kind, exists = choose(draws.target_kind, target_kinds)
    is_rect = target_kind == 0
    index, _ = choose(draws.target, jnp.where(is_rect, rect_weight, circle_weight))
    return _Target(index, is_rect, exists)


def _free_placement(draws: ShapeAddDraws, shape: SampledShape, role: Array, config: GeneratorConfig,
                    connected: Array, force_no_fixate: Array) -> tuple[Array, Array]:
    """(position, whether fixed) of an unattached shape: inside the arena with a margin, green left / blue right
    with opposite_side_chance; fixed with a chance that grows with its mass, and then moved down from the upper
    half with the bottom bias. Connected shapes are never fixed."""
    margin = jnp.maximum(_SQRT2 * shape.half.max(), shape.radius)
    low = jnp.stack([margin, margin + FLOOR_TOP])
    high = jnp.stack([ARENA_METRES - margin, ARENA_METRES - margin])
    opposite = draws.opposite_side < config.opposite_side_chance
    high = high.at[0].add(jnp.where(opposite & (role == ROLE_GREEN), -ARENA_METRES / 2.0, 0.0))
    low = low.at[0].add(jnp.where(opposite & (role == ROLE_BLUE), ARENA_METRES / 2.0, 0.0))
    position = _between(draws.free_position, low, high)
    mass = 1.0 / shape.inverse_mass
    fix_chance = jnp.minimum(config.fixate_chance_min + config.fixate_chance_scale * mass, config.fixate_chance_max)
    fixed = (draws.fixate < fix_chance) & ~force_no_fixate & ~connected
    bias = config.fixate_bottom_bias + config.fixate_bottom_bias_special_role * (role != ROLE_NEUTRAL)
    to_bottom = fixed & (draws.fixate_at_bottom < bias) & (position[1] >= ARENA_METRES / 2.0)
    return position.at[1].add(jnp.where(to_bottom, -ARENA_METRES / 2.0, 0.0)), fixed


class _Anchors(NamedTuple):
    """Where a connected shape is pinned: anchors in each shape's frame, the joint's world point, and the position
    that puts the new shape's anchor there."""

    new: Array  # [2] on the new shape
    target: Array  # [2] on the target
    world: Array  # [2]
    new_position: Array  # [2]
    target_vertices: Array  # [V, 2] the target's polygon (meaningless for a circle target)
    target_n_vertices: Array


def _anchors(draws: ShapeAddDraws, state: SimState, sizes: SceneSizes, target: _Target, is_rect: Array,
             shape: SampledShape, rotation: Array) -> _Anchors:
    """Anchors uniform in rectangles (local box) and at circle centres; the new shape is put so that they
    coincide."""
    bodies = state.bodies
    new_anchor = jnp.where(is_rect, (2.0 * draws.new_anchor - 1.0) * shape.half, 0.0)
    target_poly = jnp.minimum(target.index, sizes.num_polygons - 1)
    target_vertices = state.polygon_vertices[target_poly]
    target_n = state.polygon_n_vertices[target_poly]
    target_anchor = jnp.where(
        target.is_rect, _random_point_in_polygon(draws.target_anchor, target_vertices, target_n), jnp.zeros(2)
    )
    world = bodies.position[target.index] + rotate(bodies.rotation[target.index], target_anchor)
    return _Anchors(new_anchor, target_anchor, world, world - rotate(rotation, new_anchor), target_vertices, target_n)


def _write_shape(state: SimState, sizes: SceneSizes, index: Array, is_rect: Array, position: Array,
                 rotation: Array, shape: SampledShape, fixed: Array) -> SimState:
    """The new body and its rectangle or circle in slot `index` (-1: nothing is written), at rest, with Kinetix's
    friction, restitution and collision mode."""
    bodies = write_body(
        state.bodies, index, position=position, rotation=rotation,
        inverse_mass=jnp.where(fixed, 0.0, shape.inverse_mass),
        inverse_inertia=jnp.where(fixed, 0.0, shape.inverse_inertia),
        velocity=0.0, angular_velocity=0.0, friction=1.0, restitution=0.0, collision_mode=1,
    )
    state = write_polygon(state.replace(bodies=bodies), jnp.where(is_rect, index, -1), shape.vertices, 4)
    return write_circle(state, jnp.where(is_rect | (index < 0), -1, index - sizes.num_polygons), shape.radius)


def _write_joint(draws: ShapeAddDraws, joints: Joints, slot: Array, index: Array, target: _Target,
                 is_rect: Array, rotation: Array, target_rotation: Array, anchors: _Anchors,
                 config: GeneratorConfig, force_revolute: Array) -> tuple[Joints, Array, Array, Array]:
    """The joint between the new shape (body `index`) and the target in `slot` (-1: nothing is written), its
    bodies ordered a < b as Kinetix orders them: revolute (with a motor and, between rectangles, limits) or
    fixed. Returns the joints, the motor binding, and the anchors on sides a and b."""
    new_is_a = index < target.index
    a_index, b_index = jnp.minimum(index, target.index), jnp.maximum(index, target.index)
    a_anchor = jnp.where(new_is_a, anchors.new, anchors.target)
    b_anchor = jnp.where(new_is_a, anchors.target, anchors.new)
    rotation_a = jnp.where(new_is_a, rotation, target_rotation)
    rotation_b = jnp.where(new_is_a, target_rotation, rotation)
    revolutes = (joints.active & ~joints.is_fixed_joint).sum()
    revolute = (
        (draws.revolute < config.revolute_chance) | force_revolute | (revolutes < config.min_revolute_joints)
    )
    rect_rect = is_rect & target.is_rect
    motor_on = (draws.motor_on < config.motor_on_chance) & revolute
    speed = _between(draws.motor_speed, config.motor_min_speed, config.motor_max_speed)
    power = jnp.where(
        rect_rect,
        _between(draws.motor_power, config.motor_min_power, config.motor_max_power),
        _between(draws.wheel_power, config.motor_min_power, config.wheel_max_power),
    )
    limits = (draws.joint_limits < config.joint_limit_chance) & rect_rect & revolute
    min_rotation = jnp.where(limits, _between(draws.min_rotation, -config.joint_limit_max, 0.0), 0.0)
    max_rotation = jnp.where(limits, _between(draws.max_rotation, 0.0, config.joint_limit_max), 0.0)
    binding = jnp.minimum(jnp.floor(draws.motor_binding * NUM_MOTOR_BINDINGS), NUM_MOTOR_BINDINGS - 1).astype(jnp.int32)
    joints = write_joint(
        joints, slot,
        a_index=a_index,
        b_index=b_index,
        a_relative_pos=a_anchor,
        b_relative_pos=b_anchor,
        # Kinetix: a fixed joint holds the current relative angle; a revolute joint's reference (the origin of its
        # limits) is 0.
        rotation=jnp.where(revolute, 0.0, rotation_b - rotation_a),
        is_fixed_joint=~revolute,
        motor_on=motor_on,
        motor_speed=jnp.where(revolute, speed, 0.0),
        motor_power=jnp.where(revolute, power, 0.0),
        motor_has_joint_limits=limits,
        min_rotation=min_rotation,
        max_rotation=max_rotation,
        acc_impulse=0.0,
        acc_r_impulse=0.0,
        global_position=anchors.world,
    )
    return joints, binding, a_anchor, b_anchor


def add_shape_from_uniforms(
    u: Array,
    level: Level,
    sizes: SceneSizes,
    config: GeneratorConfig,
    connected: Array,
    force_no_fixate: Array,
    force_revolute: Array,
) -> tuple[Level, Array]:
    """Add a free shape or (if `connected`) a shape joined to an existing one. Returns the level (unchanged when
    there is no room or no target) and whether both shapes of a new joint stick out of each other (True for
    free shapes). `u` holds SHAPE_ADD_DRAWS.size uniforms. The collision filter is not refreshed here.

    The steps: find free slots and a target; draw the kind, role and dimensions; place the shape (free, or pinned
    to the target); write the body, its shape and the joint through the scene builder's writers; then the task
    data, and the visibility test that ranks proposals."""
    draws = SHAPE_ADD_DRAWS.split(u)
    connected = jnp.asarray(connected)
    state = level.state
    slots = _free_slots(level, sizes)
    target = _choose_target(draws, level, sizes, config, slots.polygon_free)

    kind, has_room = choose(draws.kind, jnp.stack([slots.polygon_free, slots.circle_free]))
    is_rect = (kind == 0) | (connected & ~target.is_rect)
    index = jnp.where(is_rect, slots.polygon, slots.circle)
    valid = has_room & (~connected | (target.exists & slots.joint_free))

    allowed = jnp.where(connected, _allowed_roles_next_to(level.roles[target.index]), 1.0)
    role = _draw_role(draws.role, level, allowed, config)
    goal = (role == ROLE_GREEN) | (role == ROLE_BLUE)
    max_size = config.max_shape_size * jnp.where(goal & ~connected, config.goal_size_factor, 1.0)
    shape = sample_shape(draws.shape, is_rect, max_size, config, sizes.max_polygon_vertices)
    rotation = draws.rotation * _TWO_PI

    free_position, fixed = _free_placement(draws, shape, role, config, connected, force_no_fixate)
    anchors = _anchors(draws, state, sizes, target, is_rect, shape, rotation)
    position = jnp.where(connected, anchors.new_position, free_position)

    body = jnp.where(valid, index, -1)
    joint = jnp.where(valid & connected, slots.joint, -1)
    target_rotation = state.bodies.rotation[target.index]
    state = _write_shape(state, sizes, body, is_rect, position, rotation, shape, fixed)
    joints, binding, a_anchor, b_anchor = _write_joint(
        draws, state.joints, joint, index, target, is_rect, rotation, target_rotation, anchors, config, force_revolute,
    )
    body_hot = jnp.arange(sizes.num_bodies) == body
    level = level.replace(
        state=state.replace(joints=joints),
        roles=put_rows(level.roles, body_hot, role),
        densities=put_rows(level.densities, body_hot, config.density),
        motor_bindings=put_rows(level.motor_bindings, jnp.arange(sizes.num_joints) == joint, binding),
    )

    # Can both shapes be seen, whatever the joint angle? (Only used to rank proposals.) Kinetix evaluates this
    # after ordering the joint's anchors by body index, so when the new shape has the higher index each shape is
    # tested at the other's anchor. We keep that: it shapes the level distribution (a new circle on a rectangle
    # then counts as hidden unless its radius exceeds the rectangle's shorter half-side plus the margin, which
    # makes large levels rectangle-heavy, as Kinetix's are).
    new_test_anchor, target_test_anchor = a_anchor, b_anchor
    target_half = local_half_extents(anchors.target_vertices, anchors.target_n_vertices)
    target_radius = circle_radius_of(state, target.index, sizes)
    new_half = jnp.where(is_rect, shape.half, 0.0)
    m = config.visibility_margin
    visible = _sticks_out(
        m, is_rect, new_half, shape.radius, new_test_anchor,
        target.is_rect, target_half, target_radius, target_test_anchor,
    ) & _sticks_out(
        m, target.is_rect, target_half, target_radius, target_test_anchor,
        is_rect, new_half, shape.radius, new_test_anchor,
    )
    return level, jnp.where(connected, visible, True)


def add_free_shape(
    key: Array, level: Level, sizes: SceneSizes, config: GeneratorConfig = GeneratorConfig(), force_no_fixate=False
) -> Level:
    """Add one unattached rectangle or circle (Kinetix's `mutate_add_shape`); no-op when no slot is free."""
    u = uniforms(key, (SHAPE_ADD_DRAWS.size,))
    level, _ = add_shape_from_uniforms(u, level, sizes, config, False, jnp.asarray(force_no_fixate), False)
    return level


def add_connected_shape(
    key: Array, level: Level, sizes: SceneSizes, config: GeneratorConfig = GeneratorConfig(), force_revolute=False
) -> tuple[Level, Array]:
    """Add one shape joined to an existing one (Kinetix's `mutate_add_connected_shape`). Returns the level (with
    a refreshed collision filter) and whether both joined shapes stick out of each other. No-op when there is no
    free shape slot, no free joint slot or no shape that can take another joint."""
    u = uniforms(key, (SHAPE_ADD_DRAWS.size,))
    level, visible = add_shape_from_uniforms(u, level, sizes, config, True, False, jnp.asarray(force_revolute))
    return level.replace(state=refresh_collision_filter(level.state)), visible


class ThrusterDraws(NamedTuple):
    target: Array  # the dynamic shape it goes on
    point_on_polygon: Array  # [2]
    angle_on_circle: Array
    distance_on_circle: Array
    aim_outward: Array  # through the centre of mass, pushing or pulling
    align_with_centre: Array  # aimed through the centre of mass at all
    free_direction: Array  # otherwise this way
    power_factor: Array
    binding: Array


THRUSTER_DRAWS = DrawLayout(ThrusterDraws, {"point_on_polygon": 2})


def add_thruster(key: Array, level: Level, sizes: SceneSizes, config: GeneratorConfig = GeneratorConfig()) -> Level:
    """Put a thruster on a random dynamic shape (Kinetix's `mutate_add_thruster`); no-op when no thruster slot is
    free or no shape is dynamic."""
    return add_thruster_from_uniforms(uniforms(key, (THRUSTER_DRAWS.size,)), level, sizes, config)


def add_thruster_from_uniforms(u: Array, level: Level, sizes: SceneSizes, config: GeneratorConfig) -> Level:
    """`add_thruster` driven by THRUSTER_DRAWS.size uniforms instead of a key."""
    if sizes.num_thrusters == 0:
        return level
    draws = THRUSTER_DRAWS.split(u)
    P = sizes.num_polygons
    state = level.state
    bodies, thrusters = state.bodies, state.thrusters
    target, has_target = choose(draws.target, bodies.active & (bodies.inverse_mass != 0))
    slot, free = first_free(thrusters.active)
    valid = has_target & free
    poly = jnp.minimum(target, P - 1)
    on_polygon = _random_point_in_polygon(draws.point_on_polygon, state.polygon_vertices[poly],
                                          state.polygon_n_vertices[poly])
    radius = circle_radius_of(state, target, sizes)
    angle = draws.angle_on_circle * _TWO_PI
    on_circle = draws.distance_on_circle * radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)])
    relative = jnp.where(target < P, on_polygon, on_circle)
    # Mostly aimed through the centre of mass (towards or away from it), otherwise at a random angle.
    aim = jnp.where(draws.aim_outward > 0.5, 1.0, -1.0) * relative
    aim = jnp.where(jnp.all(aim == 0), jnp.asarray([1.0, 0.0]), aim)
    direction = jnp.where(
        draws.align_with_centre < config.thruster_align_com_chance, jnp.arctan2(aim[1], aim[0]),
        draws.free_direction * _TWO_PI,
    )
    inverse_mass = bodies.inverse_mass[target]
    mass = 1.0 / jnp.where(inverse_mass == 0, 1.0, inverse_mass)
    factor = _between(draws.power_factor, config.thruster_min_factor, config.thruster_max_factor)
    binding = jnp.minimum(jnp.floor(draws.binding * NUM_THRUSTER_BINDINGS), NUM_THRUSTER_BINDINGS - 1).astype(jnp.int32)
    slot = jnp.where(valid, slot, -1)
    world = bodies.position[target] + rotate(bodies.rotation[target], relative)
    new = write_thruster(
        thrusters, slot, body_index=target, relative_position=relative, rotation=direction,
        power=mass * config.thruster_power_multiplier * factor, global_position=world,
    )
    hot = jnp.arange(sizes.num_thrusters) == slot
    return level.replace(
        state=state.replace(thrusters=new), thruster_bindings=put_rows(level.thruster_bindings, hot, binding)
    )


class _NewShapePairs(NamedTuple):
    """The pair lists `detect_contacts` reads, restricted to pairs with one given body (duck-types PairTables)."""

    num_rr: int
    num_cr: int
    num_cc: int
    rr_a: Array
    rr_b: Array
    cr_circle: Array
    cr_polygon: Array
    cc_a: Array
    cc_b: Array


def _others(count: int, skip: Array) -> Array:
    """0..count-1 without `skip`: count - 1 indices."""
    k = jnp.arange(count - 1, dtype=jnp.int32)
    return k + (k >= skip)


def new_shape_contacts(state: SimState, sizes: SceneSizes, poly_slot: Array, circle_slot: Array, is_rect: Array):
    """Touching contact points (as the engine's narrow phase counts them: two for a deep polygon pair) between the
    shape just written to `poly_slot` (if `is_rect`) or `circle_slot` (a body index) and every other body. Pairs
    keep the engine's orientation (lower polygon index first; the circle first in circle-polygon pairs)."""
    P, C = sizes.num_polygons, sizes.num_circles
    rr_other = _others(P, poly_slot)
    circle = circle_slot - P
    cc_other = _others(C, circle) if C > 1 else jnp.zeros((0,), jnp.int32)
    pairs = _NewShapePairs(
        num_rr=P - 1,
        num_cr=C + P,
        num_cc=max(C - 1, 0),
        rr_a=jnp.minimum(poly_slot, rr_other),
        rr_b=jnp.maximum(poly_slot, rr_other),
        # first the circles against the new polygon, then the new circle against the polygons
        cr_circle=jnp.concatenate([jnp.arange(C, dtype=jnp.int32), jnp.full((P,), circle, jnp.int32)]),
        cr_polygon=jnp.concatenate([jnp.full((C,), poly_slot, jnp.int32), jnp.arange(P, dtype=jnp.int32)]),
        cc_a=jnp.minimum(circle, cc_other),
        cc_b=jnp.maximum(circle, cc_other),
    )
    touching = detect_contacts(state, pairs).touching.astype(jnp.int32)
    rr_end = 2 * (P - 1)
    as_rect = touching[:rr_end].sum() + touching[rr_end : rr_end + C].sum()
    as_circle = touching[rr_end + C :].sum()
    return jnp.where(is_rect, as_rect, as_circle)


Proposal = Callable[[Array, Level], tuple[Level, Array]]
"""One way to add a shape: (SHAPE_ADD_DRAWS.size uniforms, level) -> (level, visible), `add_shape_from_uniforms`
with its flags bound."""


def _add_shape_filtered(u: Array, level: Level, sizes: SceneSizes, config: GeneratorConfig, propose: Proposal) -> Level:
    """The best of the proposals (one per row of `u`, [K, SHAPE_ADD_DRAWS.size]): fewest touching contact points,
    plus a penalty for a connected shape hidden by its partner. Kinetix counts every contact of the scene; all
    proposals write the same slot of the same scene, so counting only the new shape's contacts ranks them
    identically at a fraction of the cost."""
    if u.shape[0] == 1:
        return propose(u[0], level)[0]
    candidates, visible = jax.vmap(lambda row: propose(row, level))(u)
    slots = _free_slots(level, sizes)
    is_rect = candidates.state.bodies.active[:, slots.polygon] & ~level.state.bodies.active[slots.polygon]
    contacts = jax.vmap(lambda s, r: new_shape_contacts(s, sizes, slots.polygon, slots.circle, r))(
        candidates.state, is_rect
    )
    score = contacts + jnp.where(visible, 0.0, config.no_visibility_penalty)
    best = jnp.argmin(score)
    # A chain of selects rather than a gather by `best`: cheaper once vmapped over levels.
    return jax.tree.map(
        lambda x: functools.reduce(lambda acc, k: jnp.where(best == k, x[k], acc), range(1, x.shape[0]), x[0]),
        candidates,
    )


# ---------------------------------------------------------------------------------------------------------------
# Whole levels


def permute_slots(key: Array, level: Level, sizes: SceneSizes) -> Level:
    """Shuffle the non-arena polygons, the circles, the joints and the thrusters among their slots, remapping the
    joints' and thrusters' body indices. The collision filter is not refreshed here."""
    P, C, S = sizes.num_polygons, sizes.num_circles, sizes.num_static_polygons
    J, T = sizes.num_joints, sizes.num_thrusters
    u = uniforms(key, (P - S + C + J + T,))
    # argsort of uniforms: a uniformly random permutation (ties have probability ~0).
    cuts = [P - S, P - S + C, P - S + C + J]
    poly_u, circle_u, joint_u, thruster_u = jnp.split(u, cuts)
    poly_order = jnp.concatenate([jnp.arange(S), S + jnp.argsort(poly_u)]).astype(jnp.int32)
    circle_order = jnp.argsort(circle_u).astype(jnp.int32)
    joint_order, thruster_order = jnp.argsort(joint_u), jnp.argsort(thruster_u)
    order = jnp.concatenate([poly_order, P + circle_order])  # new slot i holds old body order[i]
    new_index = jnp.argsort(order).astype(jnp.int32)  # old body b is now body new_index[b]
    state = level.state
    joints, thrusters = state.joints, state.thrusters
    joints = joints.replace(a_index=new_index[joints.a_index], b_index=new_index[joints.b_index])
    thrusters = thrusters.replace(body_index=new_index[thrusters.body_index])
    state = state.replace(
        bodies=jax.tree.map(lambda x: x[order], state.bodies),
        polygon_vertices=state.polygon_vertices[poly_order],
        polygon_n_vertices=state.polygon_n_vertices[poly_order],
        circle_radius=state.circle_radius[circle_order],
        joints=jax.tree.map(lambda x: x[joint_order], joints),
        thrusters=jax.tree.map(lambda x: x[thruster_order], thrusters),
    )
    return level.replace(
        state=state,
        roles=level.roles[order],
        densities=level.densities[order],
        motor_bindings=level.motor_bindings[joint_order],
        thruster_bindings=level.thruster_bindings[thruster_order],
    )


LEVEL_ID_STREAM = 0x1D
"""`fold_in` tag that derives a random level's id from its key."""


def is_small_scene(sizes: SceneSizes, config: GeneratorConfig) -> bool:
    """Kinetix's S rule: scenes with at most `small_scene_max_shapes` shapes use 1 proposal and never fix."""
    return sizes.num_polygons + sizes.num_circles <= config.small_scene_max_shapes


class LevelDraws(NamedTuple):
    floor_role: Array
    green_may_fixate: Array  # which of green and blue may be fixed (never both)
    control: Array  # motor only, thruster only, or both
    swap_green_blue: Array
    unused: Array  # drawn, never read: kept so that every later draw stays where it was
    rest_slots: Array  # [one per remaining shape slot] connected shape, free shape or nothing
    extra_thrusters: Array  # [one per thruster slot beyond the first]


def sample_random_level(key: Array, sizes: SceneSizes, config: GeneratorConfig = GeneratorConfig()) -> Level:
    """One random level (see the module docstring). Pure; jit with `sizes` and `config` static; vmap over keys."""
    P, C, T, S = sizes.num_polygons, sizes.num_circles, sizes.num_thrusters, sizes.num_static_polygons
    small = is_small_scene(sizes, config)
    num_proposals = 1 if small else config.num_proposals
    num_rest = max(P + C - 3 - S, 0)
    num_extra = max(T - 1, 0)
    num_attempts = 4 + num_rest + num_extra
    k_level, k_attempts, k_permute = jax.random.split(key, 3)
    layout = DrawLayout(LevelDraws, {"rest_slots": num_rest, "extra_thrusters": num_extra})
    draws = layout.split(uniforms(k_level, (layout.size,)))

    level = level_from_scene(empty_scene(sizes))
    floor_role, _ = choose(draws.floor_role, jnp.asarray(config.floor_role_probs, jnp.float32))
    if S > 0:
        level = level.replace(roles=level.roles.at[0].set(floor_role))

    # The attempts, in order: green/blue free shapes (never both fixable), forced controls, the other slots,
    # extra thrusters.
    green_may_not_fix = (draws.green_may_fixate < 0.5) | (floor_role == ROLE_BLUE)
    control = jnp.floor(draws.control * 3.0)  # 0 motor only, 1 thruster only, 2 both
    force_motor, force_thruster = control != 1, control != 0
    rest_probs = jnp.asarray(
        [config.add_connected_shape_chance, config.add_free_shape_chance, config.add_nothing_chance], jnp.float32
    )
    rest_pick = jax.vmap(lambda x: choose(x, rest_probs)[0])(draws.rest_slots)
    rest_kinds = jnp.asarray([_CONNECTED_SHAPE, _FREE_SHAPE, _NOTHING], jnp.int32)[rest_pick]
    extra = draws.extra_thrusters < config.add_thruster_chance
    kinds = jnp.concatenate([
        jnp.asarray([_FREE_SHAPE, _FREE_SHAPE], jnp.int32),
        jnp.where(force_motor, _CONNECTED_SHAPE, _FREE_SHAPE)[None].astype(jnp.int32),
        jnp.where(force_thruster, _THRUSTER, _NOTHING)[None].astype(jnp.int32),
        rest_kinds,
        jnp.where(extra, _THRUSTER, _NOTHING).astype(jnp.int32),
    ])
    no_fixate = jnp.zeros((num_attempts,), bool).at[0].set(green_may_not_fix).at[1].set(~green_may_not_fix)
    no_fixate = no_fixate | small
    force_revolute = jnp.zeros((num_attempts,), bool).at[2].set(force_motor)

    def attempt(level: Level, inputs) -> tuple[Level, None]:
        kind, no_fix, revolute, k = inputs
        # Drawn here rather than for all attempts up front: a large batch then never holds every draw at once.
        row = uniforms(k, (num_proposals * SHAPE_ADD_DRAWS.size + THRUSTER_DRAWS.size,))
        shape_rows = row[: num_proposals * SHAPE_ADD_DRAWS.size].reshape(num_proposals, SHAPE_ADD_DRAWS.size)
        thruster_row = row[num_proposals * SHAPE_ADD_DRAWS.size :]
        connected = kind == _CONNECTED_SHAPE
        propose = functools.partial(
            add_shape_from_uniforms, sizes=sizes, config=config, connected=connected, force_no_fixate=no_fix,
            force_revolute=revolute,
        )
        with_shape = _add_shape_filtered(shape_rows, level, sizes, config, propose)
        with_thruster = add_thruster_from_uniforms(thruster_row, level, sizes, config)
        is_shape = (kind == _FREE_SHAPE) | connected
        pick = lambda s, t, n: jnp.where(is_shape, s, jnp.where(kind == _THRUSTER, t, n))  # noqa: E731
        return jax.tree.map(pick, with_shape, with_thruster, level), None

    attempt_keys = jax.random.split(k_attempts, num_attempts)
    level, _ = jax.lax.scan(attempt, level, (kinds, no_fixate, force_revolute, attempt_keys))

    # Swap green and blue (neutral floor only), then shuffle the slots.
    swap = (draws.swap_green_blue < config.swap_green_blue_chance) & (floor_role == ROLE_NEUTRAL)
    roles = level.roles
    swapped = jnp.where(roles == ROLE_GREEN, ROLE_BLUE, jnp.where(roles == ROLE_BLUE, ROLE_GREEN, roles))
    level = level.replace(roles=jnp.where(swap, swapped, roles))
    if config.permute_slots:
        level = permute_slots(k_permute, level, sizes)
    state = refresh_anchor_positions(refresh_collision_filter(level.state))
    # The id comes from a side stream of the key, so adding it left every other draw unchanged.
    return level.replace(state=state, level_id=random_level_id(jax.random.fold_in(key, LEVEL_ID_STREAM)))


@functools.partial(jax.jit, static_argnames=("num_levels", "sizes", "config"))
def sample_random_levels(
    key: Array, num_levels: int, sizes: SceneSizes, config: GeneratorConfig = GeneratorConfig()
) -> Level:
    """A batch of `num_levels` random levels (leading axis on every leaf), jitted."""
    keys = jax.random.split(key, num_levels)
    return jax.vmap(lambda k: sample_random_level(k, sizes, config))(keys)
