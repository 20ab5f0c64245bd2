"""A level: the physics scene plus the task data that gives it meaning (who is green, blue, red; which action
dimension drives which motor and thruster).

A `Level` is a pytree with the same static sizes as its scene, so a batch of levels is just a `Level` whose leaves
have a leading batch axis; that is how the curriculum hands levels to environments and how random levels are
sampled on a device. Roles and densities use the engine's unified body index (polygons first, then circles).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from engine.physics.pytree import pytree_dataclass
from engine.physics.sizes import SceneSizes
from engine.physics.state import SimState

Array = jax.Array

ROLE_NEUTRAL = 0
ROLE_GREEN = 1
ROLE_BLUE = 2
ROLE_RED = 3
ROLE_NAMES = ("neutral", "green", "blue", "red")

# Kinetix's action layout: four motor bindings and two thruster bindings in every size.
NUM_MOTOR_BINDINGS = 4
NUM_THRUSTER_BINDINGS = 2


@pytree_dataclass
class Level:
    """One level (or a batch of them, with a leading axis on every leaf)."""

    state: SimState
    roles: Array  # [N] int32, ROLE_* per body; only active bodies count
    densities: Array  # [N] float32, used when a mutation recomputes mass
    motor_bindings: Array  # [J] int32 in [0, NUM_MOTOR_BINDINGS)
    thruster_bindings: Array  # [T] int32 in [0, NUM_THRUSTER_BINDINGS)


def level_from_scene(
    state: SimState,
    roles: Array | None = None,
    densities: Array | None = None,
    motor_bindings: Array | None = None,
    thruster_bindings: Array | None = None,
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
