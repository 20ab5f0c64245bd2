"""What the agent sees: Kinetix's entity observation (`EntityObservation`, for set/attention networks), its flat
symbolic vector (and the same rows as a padded matrix), its pixel image (`PixelObservation`, drawn by
`engine.env.pixels`) and its blind observation (the time alone), built from the simulation and the level's task
data (roles, densities, bindings).

Every feature is computed for all slots at once (no per-slot Python loops); the pair-to-matrix layouts of the
attention mask are static numpy index tables. Layouts follow the Kinetix digest, section 7:

- Shape rows: position (2), velocity (2), inverse mass, inverse inertia, density, tanh(angular velocity / 10),
  role one-hot (4), sin and cos of rotation, friction, restitution; polygons add [0 (not a circle), the local
  vertices (unused ones -1), is-triangle], circles add [radius, 1 (circle)]; entity rows end with gravity_y / 10.
- Joint rows: [active, is_fixed, from anchor (2), to anchor (2), sin and cos of the reference rotation] then, zeroed
  for fixed joints, [motor speed, motor power, motor on, has limits, motor-binding one-hot (4), sin/cos of the
  min and max limits, min - rotation, max - rotation] (limit terms zeroed without limits). Rows 0..J-1 read
  b -> a (from = b), rows J..2J-1 read a -> b.
- Thruster rows: [active, relative position (2), thruster-binding one-hot (2), sin and cos of rotation, power].
- Attention mask channels over bodies, all restricted to active pairs: 0 every pair (self included); 1 same
  joint-connected component (self included); 2 directly jointed (both directions; entry (0, 0) always false,
  since inactive joints read (0, 0)); 3 touching in the last physics sub-step (the contact cache), stored at
  [pair_a, pair_b] of the engine's pair table only (rr as (i < j), circle-polygon as (circle, polygon)).
- Symbolic: polygon rows without walls and ceiling (slots 1..S-1 dropped), circle rows, the b -> a joint rows each
  followed by one-hot(b) and one-hot(a) over bodies, thruster rows each followed by one-hot(body), then
  gravity_y / 10; inactive rows zeroed; clipped to [-10, 10]; NaN -> 0.
- Symbolic padded (Kinetix's SYMBOLIC_FLAT_PADDED): the same rows as a matrix, each zero-padded to the widest row
  type, then its type's one-hot (polygon, circle, joint, thruster) and gravity_y / 10; clipped; NaN -> 0.
- Blind (Kinetix's BLIND): the one-hot of the agent step, length max_timesteps + 1; nothing of the scene.

Channel 1 uses the engine's collision filter (`SimState.pair_collides`: false exactly for jointed components) for
every pair the engine enumerates; arena-arena pairs, which it does not enumerate, count as connected when they are
directly jointed or share a jointed neighbour. Jax2D's own collision matrix is built joint by joint and can miss a
link when joints join two existing groups in an unlucky order; ours is the true connected component.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.env.observation_types import EntityObservation, PixelObservation
from impulse.engine.env.pixels import pixel_observation
from impulse.engine.env.spec import EnvSpec
from impulse.engine.levels.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, Level, level_from_scene
from impulse.engine.physics.building import empty_scene
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState

Array = jax.Array

NUM_ROLES = 4
NUM_ROW_TYPES = 4  # polygon, circle, joint, thruster: the padded symbolic observation's row-type one-hot
SYMBOLIC_CLIP = 10.0
BASE_SHAPE_FEATURES = 16


@dataclass(frozen=True)
class _Layout:
    """Static index tables of one size."""

    pair_at: np.ndarray  # [N, N] pair index at [pair_a, pair_b], num_pairs elsewhere (directed, for contacts)
    pair_at_sym: np.ndarray  # [N, N] the same, filled at both [a, b] and [b, a]
    kept_polygons: np.ndarray  # polygon slots in the symbolic vector (the floor and the non-arena slots)


@functools.cache
def _layout(sizes: SceneSizes) -> _Layout:
    tables = pair_tables(sizes)
    n, num_pairs = sizes.num_bodies, tables.num_pairs
    pair_at = np.full((n, n), num_pairs, np.int32)
    pair_at[tables.pair_a, tables.pair_b] = np.arange(num_pairs)
    pair_at_sym = pair_at.copy()
    pair_at_sym[tables.pair_b, tables.pair_a] = np.arange(num_pairs)
    dropped = set(range(1, sizes.num_static_polygons))
    kept = np.asarray([i for i in range(sizes.num_polygons) if i not in dropped], np.int32)
    return _Layout(pair_at, pair_at_sym, kept)


def symbolic_rows(sizes: SceneSizes) -> tuple[tuple[int, int], ...]:
    """The flat symbolic vector as consecutive (rows, features per row) blocks: kept polygons, circles, joints,
    thrusters, gravity. A row of an inactive entity is all zeros (`actors.wire` sends only the others)."""
    n = sizes.num_bodies
    polygon = BASE_SHAPE_FEATURES + 2 + 2 * sizes.max_polygon_vertices
    circle = BASE_SHAPE_FEATURES + 2
    joint = 8 + 10 + NUM_MOTOR_BINDINGS + 2 * n
    thruster = 6 + NUM_THRUSTER_BINDINGS + n
    kept = len(_layout(sizes).kept_polygons)
    return ((kept, polygon), (sizes.num_circles, circle), (sizes.num_joints, joint), (sizes.num_thrusters, thruster),
            (1, 1))


def symbolic_length(sizes: SceneSizes) -> int:
    """Length of the flat symbolic vector: 140 / 247 / 679 for Kinetix's S / M / L."""
    return sum(rows * width for rows, width in symbolic_rows(sizes))


def _shape_rows(sim: SimState, level: Level, sizes: SceneSizes) -> tuple[Array, Array]:
    """Polygon rows [P, 16 + 2 + 2V] and circle rows [C, 18], without gravity."""
    b = sim.bodies
    P = sizes.num_polygons
    column = lambda x: x[:, None].astype(jnp.float32)  # noqa: E731
    base = jnp.concatenate(
        [
            b.position,
            b.velocity,
            column(b.inverse_mass),
            column(b.inverse_inertia),
            column(level.densities),
            column(jnp.tanh(b.angular_velocity / 10.0)),
            jax.nn.one_hot(level.roles, NUM_ROLES, dtype=jnp.float32),
            column(jnp.sin(b.rotation)),
            column(jnp.cos(b.rotation)),
            column(b.friction),
            column(b.restitution),
        ],
        axis=1,
    )
    V = sizes.max_polygon_vertices
    n_vertices = sim.polygon_n_vertices
    used = (jnp.arange(V)[None, :] < n_vertices[:, None])[..., None]
    vertices = jnp.where(used, sim.polygon_vertices, -1.0).reshape(P, 2 * V)
    polygons = jnp.concatenate(
        [base[:P], jnp.zeros((P, 1), jnp.float32), vertices, column(n_vertices <= 3)], axis=1
    )
    circles = jnp.concatenate(
        [base[P:], column(sim.circle_radius), jnp.ones((sizes.num_circles, 1), jnp.float32)], axis=1
    )
    return polygons, circles


def _joint_rows(sim: SimState, level: Level) -> tuple[Array, Array]:
    """Joint rows [2J, 22] (b -> a rows, then a -> b rows) and their (from, to) body indices [2J, 2]."""
    j = sim.joints
    column = lambda x: x[:, None].astype(jnp.float32)  # noqa: E731
    limits = j.motor_has_joint_limits.astype(jnp.float32)
    revolute = 1.0 - j.is_fixed_joint.astype(jnp.float32)
    head = jnp.concatenate([column(j.active), column(j.is_fixed_joint)], axis=1)
    rotation = jnp.concatenate([column(jnp.sin(j.rotation)), column(jnp.cos(j.rotation))], axis=1)
    motor = jnp.concatenate(
        [
            column(j.motor_speed),
            column(j.motor_power),
            column(j.motor_on),
            column(j.motor_has_joint_limits),
            jax.nn.one_hot(level.motor_bindings, NUM_MOTOR_BINDINGS, dtype=jnp.float32),
            column(jnp.sin(j.min_rotation) * limits),
            column(jnp.cos(j.min_rotation) * limits),
            column(jnp.sin(j.max_rotation) * limits),
            column(jnp.cos(j.max_rotation) * limits),
            column((j.min_rotation - j.rotation) * limits),
            column((j.max_rotation - j.rotation) * limits),
        ],
        axis=1,
    ) * revolute[:, None]
    b_to_a = jnp.concatenate([head, j.b_relative_pos, j.a_relative_pos, rotation, motor], axis=1)
    a_to_b = jnp.concatenate([head, j.a_relative_pos, j.b_relative_pos, rotation, motor], axis=1)
    rows = jnp.concatenate([b_to_a, a_to_b], axis=0)
    a = jnp.where(j.active, j.a_index, 0)
    b = jnp.where(j.active, j.b_index, 0)
    indexes = jnp.concatenate([jnp.stack([b, a], axis=1), jnp.stack([a, b], axis=1)], axis=0).astype(jnp.int32)
    return rows, indexes


def _thruster_rows(sim: SimState, level: Level) -> Array:
    t = sim.thrusters
    column = lambda x: x[:, None].astype(jnp.float32)  # noqa: E731
    return jnp.concatenate(
        [
            column(t.active),
            t.relative_position,
            jax.nn.one_hot(level.thruster_bindings, NUM_THRUSTER_BINDINGS, dtype=jnp.float32),
            column(jnp.sin(t.rotation)),
            column(jnp.cos(t.rotation)),
            column(t.power),
        ],
        axis=1,
    )


def _attention_mask(sim: SimState, joint_indexes: Array, sizes: SceneSizes) -> Array:
    layout = _layout(sizes)
    n, S = sizes.num_bodies, sizes.num_static_polygons
    tables = pair_tables(sizes)
    active = sim.bodies.active
    both = active[:, None] & active[None, :]
    eye = np.eye(n, dtype=bool)

    body = jnp.arange(n)
    from_hit = joint_indexes[:, 0:1] == body[None, :]
    to_hit = joint_indexes[:, 1:2] == body[None, :]
    one_hop = jnp.any(from_hit[:, :, None] & to_hit[:, None, :], axis=0).at[0, 0].set(False)

    # Same component: the engine's collision filter for enumerated pairs (false = jointed together).
    linked = jnp.concatenate([~sim.pair_collides, jnp.zeros((1,), bool)])[layout.pair_at_sym]
    if S > 1:
        # Arena-arena pairs are not enumerated: directly jointed, or sharing a jointed neighbour.
        shared = jnp.any(linked[:S, None, :] & linked[None, :S, :], axis=-1)
        linked = linked.at[:S, :S].set(shared | one_hop[:S, :S])
    same_component = linked | eye

    # Point 0 of each pair (a polygon pair's point 1 only touches when point 0 does).
    touching = jnp.concatenate([sim.contacts.active[: tables.num_rr], sim.contacts.active[2 * tables.num_rr :]])
    contact = jnp.concatenate([touching, jnp.zeros((1,), bool)])[layout.pair_at]

    return jnp.stack([both, same_component & both, one_hop & both, contact & both])


def entity_observation(sim: SimState, level: Level, sizes: SceneSizes) -> EntityObservation:
    """Kinetix's SYMBOLIC_ENTITY observation of one environment (unclipped; NaN -> 0)."""
    P = sizes.num_polygons
    gravity = jnp.nan_to_num(sim.gravity[1]) / 10.0
    polygons, circles = _shape_rows(sim, level, sizes)
    polygons = jnp.concatenate([polygons, jnp.full((P, 1), gravity)], axis=1)
    circles = jnp.concatenate([circles, jnp.full((sizes.num_circles, 1), gravity)], axis=1)
    joints, joint_indexes = _joint_rows(sim, level)
    active = sim.bodies.active
    return EntityObservation(
        polygons=jnp.nan_to_num(polygons),
        circles=jnp.nan_to_num(circles),
        joints=jnp.nan_to_num(joints),
        thrusters=jnp.nan_to_num(_thruster_rows(sim, level)),
        polygon_mask=active[:P],
        circle_mask=active[P:],
        joint_mask=jnp.concatenate([sim.joints.active, sim.joints.active]),
        thruster_mask=sim.thrusters.active,
        joint_indexes=joint_indexes,
        thruster_indexes=sim.thrusters.body_index.astype(jnp.int32),
        attention_mask=_attention_mask(sim, joint_indexes, sizes),
    )


def _symbolic_blocks(sim: SimState, level: Level, sizes: SceneSizes) -> tuple[Array, Array, Array, Array]:
    """The symbolic rows by type, inactive rows zeroed: kept polygons, circles, b -> a joints (with one-hot(b) and
    one-hot(a) over bodies) and thrusters (with one-hot(body)); unclipped."""
    layout = _layout(sizes)
    n, P, J = sizes.num_bodies, sizes.num_polygons, sizes.num_joints
    active = sim.bodies.active
    polygons, circles = _shape_rows(sim, level, sizes)
    polygons = jnp.where(active[layout.kept_polygons, None], polygons[layout.kept_polygons], 0.0)
    circles = jnp.where(active[P:, None], circles, 0.0)
    joints, indexes = _joint_rows(sim, level)
    joints = jnp.concatenate(
        [joints[:J], jax.nn.one_hot(indexes[:J, 0], n), jax.nn.one_hot(indexes[:J, 1], n)], axis=1
    )
    joints = jnp.where(sim.joints.active[:, None], joints, 0.0)
    thrusters = jnp.concatenate([_thruster_rows(sim, level), jax.nn.one_hot(sim.thrusters.body_index, n)], axis=1)
    thrusters = jnp.where(sim.thrusters.active[:, None], thrusters, 0.0)
    return polygons, circles, joints, thrusters


def _clipped(features: Array) -> Array:
    return jnp.nan_to_num(jnp.clip(features, -SYMBOLIC_CLIP, SYMBOLIC_CLIP))


def symbolic_observation(sim: SimState, level: Level, sizes: SceneSizes) -> Array:
    """Kinetix's SYMBOLIC_FLAT observation of one environment: a float32 vector of `symbolic_length(sizes)`."""
    blocks = _symbolic_blocks(sim, level, sizes)
    gravity = (sim.gravity[1:2] / 10.0).astype(jnp.float32)
    return _clipped(jnp.concatenate([block.reshape(-1) for block in blocks] + [gravity]))


def symbolic_padded_shape(sizes: SceneSizes) -> tuple[int, int]:
    """(rows, width) of the padded symbolic observation: one row per kept polygon, circle, joint and thruster;
    the widest row type, then the row type's one-hot and gravity (Kinetix S (6, 41), M (10, 45), L (21, 59))."""
    blocks = symbolic_rows(sizes)[:4]
    return sum(rows for rows, _ in blocks), max(width for _, width in blocks) + NUM_ROW_TYPES + 1


def symbolic_padded_observation(sim: SimState, level: Level, sizes: SceneSizes) -> Array:
    """Kinetix's SYMBOLIC_FLAT_PADDED observation of one environment: the flat observation's rows as a
    [rows, width] matrix (`symbolic_padded_shape`), each row right-padded with zeros to the widest type, followed
    by the one-hot of its type (polygon, circle, joint, thruster) and gravity_y / 10; clipped, NaN -> 0."""
    blocks = _symbolic_blocks(sim, level, sizes)
    rows, width = symbolic_padded_shape(sizes)
    features = width - NUM_ROW_TYPES - 1
    padded = [jnp.pad(block, ((0, 0), (0, features - block.shape[1]))) for block in blocks]
    row_type = np.repeat(np.arange(NUM_ROW_TYPES), [block.shape[0] for block in blocks])
    gravity = jnp.full((rows, 1), sim.gravity[1] / 10.0, jnp.float32)
    matrix = jnp.concatenate(
        [jnp.concatenate(padded, axis=0), jax.nn.one_hot(row_type, NUM_ROW_TYPES, dtype=jnp.float32), gravity], axis=1
    )
    return _clipped(matrix)


def blind_observation(timestep: Array | int, max_timesteps: int) -> Array:
    """Kinetix's BLIND observation: only the time, as the one-hot of the agent step (length max_timesteps + 1)."""
    return jax.nn.one_hot(timestep, max_timesteps + 1, dtype=jnp.float32)


def observe(
    spec: EnvSpec, sim: SimState, level: Level, timestep: Array | int = 0
) -> EntityObservation | PixelObservation | Array:
    """The observation `spec.observation` names, of a scene at agent step `timestep` (only "blind" reads it)."""
    if spec.observation == "entity":
        return entity_observation(sim, level, spec.sizes)
    if spec.observation == "pixels":
        return pixel_observation(sim, level, spec.sizes, spec.pixel_downscale)
    if spec.observation == "symbolic_padded":
        return symbolic_padded_observation(sim, level, spec.sizes)
    if spec.observation == "blind":
        return blind_observation(timestep, spec.max_timesteps)
    return symbolic_observation(sim, level, spec.sizes)


def observation_shape(spec: EnvSpec) -> EntityObservation | PixelObservation | jax.ShapeDtypeStruct:
    """Shapes and dtypes of one environment's observation (for initialising networks), without running anything
    heavier than abstract evaluation."""
    level = level_from_scene(empty_scene(spec.sizes))
    return jax.eval_shape(lambda lv: observe(spec, lv.state, lv), level)
