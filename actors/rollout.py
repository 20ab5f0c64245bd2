"""The rollout: a batch of environments driven by the policy for T steps, as one `lax.scan`.

This is the only place experience is generated. The fused trainer calls it inside its jitted loop; actor
processes call it (jitted on its own) and publish what it returns. It knows nothing of networks: it takes a
`policy(params, obs, key) -> (action, log_prob, value)` over a batch of observations, so any network fits.

Levels reach the environments through `levels` (a `Level` batch of K, shared by all environments): an episode
that ends restarts on the next level of the batch (see `engine.env.env`). Every step records the id of the level
it was played on (`EnvState.level`), so results are credited by level id even when the caller swaps the batch
while episodes are running (`actors.trajectory.level_results`). The caller wraps the steps into a
`TrajectoryBatch` with the bootstrap observation (`carry.obs` after the rollout) and its policy version.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from actors.trajectory import Trajectory
from engine.env.env import step as env_step
from engine.env.spec import EnvParams, EnvSpec
from engine.env.state import EnvState
from engine.levels.level import Level

Array = jax.Array
Policy = Callable[[Any, Any, Array], tuple[Array, Array, Array]]


class RolloutCarry(NamedTuple):
    """What one rollout hands to the next."""

    env_state: EnvState  # [E]
    obs: Any  # [E, ...] observation of env_state
    key: Array


class RolloutStats(NamedTuple):
    """Whole-batch summaries of the episodes that ended during the rollout."""

    episodes: Array
    solved: Array
    failed: Array
    timed_out: Array
    nan: Array
    return_sum: Array
    length_sum: Array


def rollout(
    policy: Policy,
    params: Any,
    spec: EnvSpec,
    env_params: EnvParams,
    carry: RolloutCarry,
    levels: Level,
    num_steps: int,
) -> tuple[RolloutCarry, Trajectory, RolloutStats]:
    """Run `num_steps` steps of every environment. Returns (carry, steps [T, E], whole-batch episode stats)."""
    step_all = jax.vmap(env_step, in_axes=(None, None, 0, 0, None))

    def one_step(carry: RolloutCarry, _):
        env_state, obs, key = carry
        key, act_key = jax.random.split(key)
        action, log_prob, value = policy(params, obs, act_key)
        level_id = env_state.level.level_id
        next_obs, env_state, reward, done, info = step_all(spec, env_params, env_state, action, levels)
        finished_return = jnp.where(done, info["returned_episode_return"], 0.0)
        transition = Trajectory(
            obs=obs,
            action=action,
            log_prob=log_prob,
            value=value,
            reward=reward,
            done=done,
            solved=info["solved"],
            truncated=info["timed_out"],
            episode_return=finished_return,
            level_id=level_id,
        )
        episode = RolloutStats(
            episodes=done.astype(jnp.int32).sum(),
            solved=info["solved"].sum(),
            failed=info["failed"].sum(),
            timed_out=info["timed_out"].sum(),
            nan=info["nan"].sum(),
            return_sum=finished_return.sum(),
            length_sum=jnp.where(done, info["returned_episode_length"], 0).sum(),
        )
        return RolloutCarry(env_state, next_obs, key), (transition, episode)

    carry, (trajectory, per_step) = jax.lax.scan(one_step, carry, None, length=num_steps)
    stats = jax.tree.map(lambda x: x.sum(), per_step)
    return carry, trajectory, stats
