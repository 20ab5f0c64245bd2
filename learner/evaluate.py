"""Evaluation: each level played `attempts` times from its start, one episode per attempt, as Kinetix scores its
hand-made levels (solve rate = fraction of attempts whose episode ended with green touching blue).

All K x attempts episodes run side by side in one jitted scan of `max_timesteps` steps; an environment's first
episode is the one counted, whatever it does after its auto-reset.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from engine.env.env import reset_batch
from engine.env.env import step as env_step
from engine.env.spec import EnvParams
from engine.levels.level import Level
from learner.agent import Agent

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
    spec = agent.spec
    batch = _repeat(levels, attempts)
    num_envs = batch.roles.shape[0]
    obs, state = reset_batch(spec, env_params, batch, num_envs)
    act = agent.act_greedy if greedy else agent.act
    step_all = jax.vmap(env_step, in_axes=(None, None, 0, 0, None))

    def one_step(carry, step_key):
        obs, state, finished, solved, failed, ret, length = carry
        action, _, _ = act(params, obs, step_key)
        obs, state, _, done, info = step_all(spec, env_params, state, action, batch)
        first = done & ~finished
        solved = solved | (first & info["solved"])
        failed = failed | (first & info["failed"])
        ret = jnp.where(first, info["returned_episode_return"], ret)
        length = jnp.where(first, info["returned_episode_length"], length)
        return (obs, state, finished | done, solved, failed, ret, length), None

    false = jnp.zeros(num_envs, bool)
    start = (obs, state, false, false, false, jnp.zeros(num_envs), jnp.zeros(num_envs, jnp.int32))
    keys = jax.random.split(key, spec.max_timesteps)
    (_, _, _, solved, failed, ret, length), _ = jax.lax.scan(one_step, start, keys)
    shape = (levels.roles.shape[0], attempts)
    return solved.reshape(shape), failed.reshape(shape), ret.reshape(shape), length.reshape(shape)


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
