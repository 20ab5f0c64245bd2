"""Playing scripted controllers (`engine.levels.handmade.controllers`) through the environment, for tests and demos.

A controller maps (simulation state, agent step of the episode) to one environment's multi-discrete action; here
each environment's controller drives it through the engine's episode loop and the outcome of its first episode is
kept. The controllers live with the levels they solve; the runner lives here because playing needs the
environment, which the level package does not import.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.env.episodes import first_episodes
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.env.state import EnvState
from impulse.engine.levels.handmade.controllers import Controller
from impulse.engine.levels.level import Level
from impulse.engine.physics.state import SimState

Array = jax.Array


class Outcome(NamedTuple):
    """How the first episode ended: `steps` = agent steps taken (the step that ended it included), or the number
    of steps played if it did not end; `solved` / `failed` as in the environment's info."""

    solved: Array
    failed: Array
    steps: Array


@functools.partial(jax.jit, static_argnums=(0, 3, 5))
def play_batch(
    spec: EnvSpec,
    params: EnvParams,
    levels: Level,
    controllers: tuple[Controller, ...],
    which: Array,
    num_steps: int = 256,
) -> Outcome:
    """Play a batch of levels [B] at once, level i with `controllers[which[i]]` (one compilation for any mix of
    levels and controllers of one size)."""

    def one(sim: SimState, t: Array, index: Array) -> Array:
        return jax.lax.switch(index, controllers, sim, t)

    def act(obs: Any, state: EnvState, key: Array | None) -> tuple[Array, None]:
        # The episode's own step count: within the first episode (the one kept) it counts from 0 like the scan.
        return jax.vmap(one)(state.sim, state.timestep, which), None

    first = first_episodes(spec, params, levels, num_steps, act)
    return Outcome(first.solved, first.failed, first.length)


def play(spec: EnvSpec, params: EnvParams, level: Level, controller: Controller, num_steps: int = 256) -> Outcome:
    """Play `controller` on one `level` for up to `num_steps` agent steps."""
    one = jax.tree.map(lambda x: x[None], level)
    outcome = play_batch(spec, params, one, (controller,), jnp.zeros(1, jnp.int32), num_steps)
    return jax.tree.map(lambda x: x[0], outcome)
