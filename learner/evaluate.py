"""Evaluation: each level played `attempts` times from its start, one episode per attempt, as Kinetix scores its
hand-made levels (solve rate = fraction of attempts whose episode ended with green touching blue).

All K x attempts episodes run side by side in one jitted scan of `max_timesteps` steps; an environment's first
episode is the one counted, whatever it does after its auto-reset.

`record_episodes` plays one more episode per level through the rollout with every environment watched, so that
`impulse eval --record` can draw them (`monitor.rollouts`) with the same code that draws live rollouts, and
`impulse eval --video` as a video (`monitor.video`). `play_episodes` is the same with any policy, or none (the
no-op action throughout: `impulse levels render --video` shows a level's own dynamics that way).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.actors.rollout import Policy, Watched, rollout, start_rollout
from impulse.actors.trajectory import Trajectory
from impulse.engine.env.actions import noop_action
from impulse.engine.env.episodes import first_episodes
from impulse.engine.env.spec import EnvParams, EnvSpec
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
    """Play each of `levels` [K] once from its start with the agent's policy, recording every step for drawing."""
    return play_episodes(agent.act_greedy if greedy else agent.act, params, agent.spec, env_params, levels, key)


def play_episodes(policy: Policy | None, params: Any, spec: EnvSpec, env_params: EnvParams, levels: Level,
                  key: Array) -> RecordedEpisodes:
    """Play each of `levels` [K] once from its start for at most `spec.max_timesteps` agent steps, recording every
    step for drawing. `policy` None: the no-op action at every step (`engine.env.actions.noop_action`)."""
    policy = policy if policy is not None else noop_policy(spec)
    num_levels = levels.roles.shape[0]

    def play(levels: Level, key: Array) -> Any:  # one program: the reset too, not an eager op at a time
        carry = start_rollout(spec, env_params, levels, num_levels, key)
        return rollout(policy, params, spec, env_params, carry, levels, spec.max_timesteps, watch=num_levels)

    played = jax.jit(play)(levels, key)
    done = np.asarray(played.steps.done)
    ended_before = np.cumsum(done, axis=0) - done
    return RecordedEpisodes(played.watched, jax.device_get(played.steps), ended_before == 0)


def noop_policy(spec: EnvSpec) -> Policy:
    """A rollout policy that drives nothing: the no-op action for every environment (log-probability and value 0)."""
    action = noop_action(spec)

    def act(params: Any, obs: Any, key: Array) -> tuple[Array, Array, Array]:
        num = jax.tree.leaves(obs)[0].shape[0]
        return jnp.broadcast_to(action, (num, *action.shape)), jnp.zeros(num), jnp.zeros(num)

    return act
