"""The rollout: a batch of environments driven by the policy for T steps, as one `lax.scan`.

This is the only place experience is generated. The fused trainer calls it inside its jitted loop; actor
processes call it (jitted on its own) and publish what it returns. It knows nothing of networks: it takes a
`policy(params, obs, key) -> (action, log_prob, value)` over a batch of observations, so any network fits.

Levels reach the environments through `levels` (a `Level` batch of K, shared by all environments): an episode
that ends restarts on the next level of the batch (see `engine.env.env`). The rollout also tallies, per level of
the batch, how many episodes ended there and how many were solved; that is what a curriculum scores levels by.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from engine.env.env import step as env_step
from engine.env.spec import EnvParams, EnvSpec
from engine.env.state import EnvState
from engine.levels.level import Level

Array = jax.Array
Policy = Callable[[Any, Any, Array], tuple[Array, Array, Array]]


class Trajectory(NamedTuple):
    """Time-major experience of E environments over T steps (leaves [T, E, ...])."""

    obs: Any  # the observation the action was chosen from
    action: Array
    log_prob: Array  # of the action under the behaviour policy
    value: Array  # the behaviour policy's value estimate of obs
    reward: Array
    done: Array  # the step ended an episode (the next obs belongs to a fresh one)
    solved: Array  # the episode ended with green touching blue on this step
    truncated: Array  # the episode was cut off by the time limit on this step (not a terminal state)


class RolloutCarry(NamedTuple):
    """What one rollout hands to the next."""

    env_state: EnvState  # [E]
    obs: Any  # [E, ...] observation of env_state
    key: Array


class LevelResults(NamedTuple):
    """Per level of the batch (leaves [K]): episodes that ended on it during the rollout."""

    episodes: Array  # int32
    solved: Array  # int32
    return_sum: Array  # float32, sum of the finished episodes' returns


class RolloutStats(NamedTuple):
    """Whole-batch summaries of the episodes that ended during the rollout."""

    episodes: Array
    solved: Array
    failed: Array
    timed_out: Array
    nan: Array
    return_sum: Array
    length_sum: Array


def current_level_index(env_state: EnvState, num_levels: int) -> Array:
    """Index into the level batch of the level each environment is playing now (its `next_level` minus one)."""
    return (env_state.next_level - 1) % num_levels


def rollout(
    policy: Policy,
    params: Any,
    spec: EnvSpec,
    env_params: EnvParams,
    carry: RolloutCarry,
    levels: Level,
    num_steps: int,
) -> tuple[RolloutCarry, Trajectory, Array, LevelResults, RolloutStats]:
    """Run `num_steps` steps of every environment. Returns (carry, trajectory, last value, per-level results,
    stats); the last value is the policy's estimate for the final observation, which bootstraps returns."""
    num_levels = levels.roles.shape[0]
    step_all = jax.vmap(env_step, in_axes=(None, None, 0, 0, None))

    def one_step(state: tuple[RolloutCarry, LevelResults], _):
        (env_state, obs, key), results = state
        key, act_key = jax.random.split(key)
        action, log_prob, value = policy(params, obs, act_key)
        playing = current_level_index(env_state, num_levels)
        next_obs, env_state, reward, done, info = step_all(spec, env_params, env_state, action, levels)
        ended = done.astype(jnp.int32)
        results = LevelResults(
            episodes=results.episodes.at[playing].add(ended),
            solved=results.solved.at[playing].add(info["solved"].astype(jnp.int32)),
            return_sum=results.return_sum.at[playing].add(jnp.where(done, info["returned_episode_return"], 0.0)),
        )
        transition = Trajectory(
            obs=obs,
            action=action,
            log_prob=log_prob,
            value=value,
            reward=reward,
            done=done,
            solved=info["solved"],
            truncated=info["timed_out"],
        )
        episode = RolloutStats(
            episodes=ended.sum(),
            solved=info["solved"].sum(),
            failed=info["failed"].sum(),
            timed_out=info["timed_out"].sum(),
            nan=info["nan"].sum(),
            return_sum=jnp.where(done, info["returned_episode_return"], 0.0).sum(),
            length_sum=jnp.where(done, info["returned_episode_length"], 0).sum(),
        )
        return (RolloutCarry(env_state, next_obs, key), results), (transition, episode)

    empty = LevelResults(
        episodes=jnp.zeros(num_levels, jnp.int32),
        solved=jnp.zeros(num_levels, jnp.int32),
        return_sum=jnp.zeros(num_levels, jnp.float32),
    )
    (carry, results), (trajectory, per_step) = jax.lax.scan(one_step, (carry, empty), None, length=num_steps)
    key, last_key = jax.random.split(carry.key)
    _, _, last_value = policy(params, carry.obs, last_key)
    stats = jax.tree.map(lambda x: x.sum(), per_step)
    return carry._replace(key=key), trajectory, last_value, results, stats
