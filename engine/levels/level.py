"""A level: the physics scene plus the task data that gives it meaning (who is green, blue, red; which action
dimension drives which motor and thruster).

A `Level` is a pytree with the same static sizes as its scene, so a batch of levels is just a `Level` whose leaves
have a leading batch axis; that is how the curriculum hands levels to environments and how random levels are
sampled on a device. Roles and densities use the engine's unified body index (polygons first, then circles).

Every level carries a 64-bit id, unique within a run, by which every process names it: the environment state
holds the level it plays (so its id), trajectories record the id of every environment's level at every step,
and per-level results are reported by id, never by a slot of whatever batch is current. JAX runs without 64-bit
integers, so the id is stored as two uint32 words (high, low); `level_id_values` joins them on the host. Files
and our hand-made levels get a content hash (the same level loaded twice is the same level); random and mutated
levels get ids drawn from their random key on the device. Id 0 means "not assigned".
"""

from __future__ import annotations

import hashlib

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState
from impulse.engine.pytree import pytree_dataclass

Array = jax.Array

ROLE_NEUTRAL = 0
ROLE_GREEN = 1
ROLE_BLUE = 2
ROLE_RED = 3
ROLE_NAMES = ("neutral", "green", "blue", "red")

# Kinetix's action layout: four motor bindings and two thruster bindings in every size.
NUM_MOTOR_BINDINGS = 4
NUM_THRUSTER_BINDINGS = 2

LEVEL_ID_WORDS = 2
"""A level id is stored as this many uint32 words, most significant first."""
UNASSIGNED_LEVEL_ID = 0


@pytree_dataclass
class Level:
    """One level (or a batch of them, with a leading axis on every leaf)."""

    state: SimState
    roles: Array  # [N] int32, ROLE_* per body; only active bodies count
    densities: Array  # [N] float32, used when a mutation recomputes mass
    motor_bindings: Array  # [J] int32 in [0, NUM_MOTOR_BINDINGS)
    thruster_bindings: Array  # [T] int32 in [0, NUM_THRUSTER_BINDINGS)
    level_id: Array  # [LEVEL_ID_WORDS] uint32, the 64-bit id as (high, low) words


def level_from_scene(
    state: SimState,
    roles: Array | None = None,
    densities: Array | None = None,
    motor_bindings: Array | None = None,
    thruster_bindings: Array | None = None,
    level_id: int = UNASSIGNED_LEVEL_ID,
) -> Level:
    """Wrap a scene as a level; task data left out defaults to neutral roles, density 1 and binding 0."""
    num_bodies = state.bodies.active.shape[-1]
    num_joints = state.joints.active.shape[-1]
    num_thrusters = state.thrusters.active.shape[-1]

    def array_or(value, shape, fill, dtype):
        return jnp.full(shape, fill, dtype) if value is None else jnp.asarray(value, dtype)

    return Level(
        state=state,
        roles=array_or(roles, (num_bodies,), ROLE_NEUTRAL, jnp.int32),
        densities=array_or(densities, (num_bodies,), 1.0, jnp.float32),
        motor_bindings=array_or(motor_bindings, (num_joints,), 0, jnp.int32),
        thruster_bindings=array_or(thruster_bindings, (num_thrusters,), 0, jnp.int32),
        level_id=jnp.asarray(level_id_words(level_id)),
    )


def level_sizes(level: Level, sizes: SceneSizes) -> bool:
    """Whether `level`'s (unbatched) arrays have the slot counts of `sizes`."""
    return (
        level.roles.shape[-1] == sizes.num_bodies
        and level.motor_bindings.shape[-1] == sizes.num_joints
        and level.thruster_bindings.shape[-1] == sizes.num_thrusters
    )


def stack_levels(levels: list[Level]) -> Level:
    """A batch from levels of equal sizes (the leading axis indexes the levels)."""
    if not levels:
        raise ValueError("stack_levels needs at least one level")
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *levels)


def level_id_words(value: int) -> np.ndarray:
    """The uint32 (high, low) words of a 64-bit level id."""
    if not 0 <= value < 1 << 64:
        raise ValueError(f"level id {value} is not a 64-bit unsigned integer")
    return np.asarray([value >> 32, value & 0xFFFFFFFF], np.uint32)


def level_id_values(words) -> np.ndarray:
    """Level ids as uint64 from their words (any leading shape, last axis LEVEL_ID_WORDS); host side."""
    words = np.asarray(words, np.uint64)
    return (words[..., 0] << np.uint64(32)) | words[..., 1]


def random_level_id(key: Array) -> Array:
    """A fresh id drawn from `key` (jittable): a 63-bit random number, never the unassigned id 0."""
    words = jax.random.bits(key, (LEVEL_ID_WORDS,), jnp.uint32)
    return words.at[-1].set(words[-1] | jnp.uint32(1))


def content_level_id(level: Level) -> int:
    """A hash of everything in one (unbatched) level except its id: equal levels get equal ids (every NaN is one
    NaN and -0.0 is 0.0, as in an element-wise comparison). Host side."""
    digest = hashlib.blake2b(digest_size=8)
    for leaf in jax.tree.leaves(level.replace(level_id=np.zeros(LEVEL_ID_WORDS, np.uint32))):
        array = np.ascontiguousarray(np.asarray(leaf))
        if array.dtype.kind == "f":
            array = np.where(np.isnan(array), np.nan, array + 0.0).astype(array.dtype)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return int.from_bytes(digest.digest(), "little") | 1


def with_content_id(level: Level) -> Level:
    """`level` with its id set to its content hash."""
    return level.replace(level_id=jnp.asarray(level_id_words(content_level_id(level))))
