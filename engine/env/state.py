"""The environment's state: the simulation plus the episode bookkeeping, one pytree per environment (a batch of
environments adds a leading axis to every leaf)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from impulse.engine.levels.level import Level
from impulse.engine.physics.state import SimState
from impulse.engine.pytree import pytree_dataclass

Array = jax.Array

UNSET_DISTANCE = -1.0
"""`last_distance` before the first step of an episode: no dense reward is paid on that step (Kinetix's rule)."""


@pytree_dataclass
class EnvState:
    sim: SimState
    level: Level  # the level this episode started from (its roles, densities and bindings are read every step)
    timestep: Array  # int32 agent steps since the reset
    last_distance: Array  # float32 green-blue distance after the previous step; UNSET_DISTANCE after a reset
    episode_return: Array  # float32 sum of rewards so far this episode
    episode_length: Array  # int32 agent steps so far this episode (equals timestep)
    next_level: Array  # int32 index into the caller's level batch taken at the next auto-reset (modulo its size)


def initial_state(level: Level, next_level: Array | int = 0) -> EnvState:
    """The state at the start of an episode on `level`."""
    return EnvState(
        sim=level.state,
        level=level,
        timestep=jnp.zeros((), jnp.int32),
        last_distance=jnp.full((), UNSET_DISTANCE, jnp.float32),
        episode_return=jnp.zeros((), jnp.float32),
        episode_length=jnp.zeros((), jnp.int32),
        next_level=jnp.asarray(next_level, jnp.int32),
    )
