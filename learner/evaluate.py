"""Evaluation: each level played `attempts` times from its start, one episode per attempt, as Kinetix scores its
hand-made levels (solve rate = fraction of attempts whose episode ended with green touching blue).

All K x attempts episodes run side by side in one jitted scan of `max_timesteps` steps; an environment's first
episode is the one counted, whatever it does after its auto-reset.

`record_episodes` plays one more episode per level through the rollout with every environment watched, so that
`impulse eval --record` can draw them (`monitor.rollouts`) with the same code that draws live rollouts.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from impulse.actors.rollout import Watched, rollout, start_rollout
from impulse.actors.trajectory import Trajectory
from impulse.engine.env.episodes import first_episodes
from impulse.engine.env.spec import EnvParams
from impulse.engine.env.state import EnvState
from impulse.engine.levels.level import Level
from impulse.learner.agent import Agent

Array = jax.Array


class LevelScores(NamedTuple):
    """Per level [K]."""

    solve_rate: np.ndarray
    mean_return: np.ndarray
    mean_length: np.ndarray
    failed_rate: np.ndarray


def _repeat(levels: Level, attempts: int) -> Level:
    return jax.tree.map(lambda x: jnp.repeat(x, attempts, axis=0), levels)


@functools.partial(jax.jit, static_argnames=("agent", "attempts", "greedy"))
def _play(agent: Agent, params: Any, env_params: EnvParams, levels: Level, key: Array, attempts: int, greedy: bool):
    policy = agent.act_greedy if greedy else agent.act

    def act(obs: Any, state: EnvState, step_key: Array) -> tuple[Array, None]:
        return policy(params, obs, step_key)[0], None

    spec = agent.spec
    first = first_episodes(spec, env_params, _repeat(levels, attempts), spec.max_timesteps, act, key)
    shape = (levels.roles.shape[0], attempts)
    return tuple(x.reshape(shape) for x in (first.solved, first.failed, first.episode_return, first.length))


def evaluate(
    agent: Agent,
    params: Any,
    env_params: EnvParams,
    levels: Level,
    key: Array,
    attempts: int = 20,
    greedy: bool = False,
) -> LevelScores:
    """Solve rate, mean return and length per level over `attempts` episodes (stochastic policy unless greedy)."""
    played = _play(agent, params, env_params, levels, key, attempts, greedy)
    solved, failed, ret, length = (np.asarray(x) for x in played)
    return LevelScores(
        solve_rate=solved.mean(axis=1),
        mean_return=ret.mean(axis=1),
        mean_length=length.mean(axis=1),
        failed_rate=failed.mean(axis=1),
    )


def solve_rates(agent: Agent, params: Any, env_params: EnvParams, levels: Level, key: Array, attempts: int,
                greedy: bool = False) -> Array:
    """The fraction of `attempts` episodes solved on each of `levels` [K], as a traced array, so that a jitted
    caller can score levels inside its own step (the fused trainer's batch-scored SFL, `learner.fused`)."""
    solved, *_ = _play(agent, params, env_params, levels, key, attempts, greedy)
    return solved.mean(axis=1)


class RecordedEpisodes(NamedTuple):
    """One episode per level, [T, K]: T = the longest episode allowed, K levels (environment k plays level k)."""

    watched: Watched
    steps: Trajectory
    first: np.ndarray  # [T, K] bool: the step belongs to the level's first episode (the one recorded)


def record_episodes(agent: Agent, params: Any, env_params: EnvParams, levels: Level, key: Array,
                    greedy: bool = False) -> RecordedEpisodes:
    """Play each of `levels` [K] once from its start, recording every step for drawing."""
    spec = agent.spec
    policy = agent.act_greedy if greedy else agent.act
    num_levels = levels.roles.shape[0]
    carry = start_rollout(spec, env_params, levels, num_levels, key)
    played = jax.jit(lambda c: rollout(policy, params, spec, env_params, c, levels, spec.max_timesteps,
                                       watch=num_levels))(carry)
    done = np.asarray(played.steps.done)
    ended_before = np.cumsum(done, axis=0) - done
    return RecordedEpisodes(played.watched, jax.device_get(played.steps), ended_before == 0)
