"""Fused training: level sampling, rollout and PPO update composed into one jitted iteration on one device.

The iteration is the same rollout (`actors.rollout.rollout`) and update (`learner.update.ppo_update`) that the
distributed services use, so fused mode is both the fastest single-device trainer and the baseline the
distributed mode is measured against.

Everything an iteration depends on lives in `FusedCarry` (parameters, optimiser state, every environment's state
and observation, the random key), and the iteration is a pure function of it. Checkpointing the carry therefore
makes a resumed run continue bit for bit.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from actors.rollout import RolloutCarry, rollout
from actors.trajectory import make_batch
from engine.env.env import reset_batch
from engine.env.spec import EnvParams, EnvSpec
from engine.levels.level import Level
from learner.agent import Agent
from learner.config import PPOConfig
from learner.update import TrainState, make_optimizer, ppo_update

Array = jax.Array
LevelSampler = Callable[[Array], Level]  # key -> a batch of levels


class FusedCarry(NamedTuple):
    train: TrainState
    envs: RolloutCarry
    key: Array


@dataclass(frozen=True)
class FusedTrainer:
    """The static parts of a fused run; `init` and `iterate` are its two pure (jitted) functions."""

    agent: Agent
    env_params: EnvParams
    ppo: PPOConfig
    num_updates: int
    sample_levels: LevelSampler | None = None
    """For random levels: a fresh batch per iteration. None: the fixed batch passed to `iterate`."""

    @property
    def spec(self) -> EnvSpec:
        return self.agent.spec

    @functools.cached_property
    def optimizer(self):
        return make_optimizer(self.ppo, self.num_updates)

    def init(self, key: Array, levels: Level | None) -> FusedCarry:
        """Fresh parameters and `ppo.num_envs` environments started on the level batch (staggered)."""
        init_key, level_key, env_key, key = jax.random.split(key, 4)
        params = self.agent.init(init_key)
        train = TrainState(params, self.optimizer.init(params), jnp.zeros((), jnp.int32))
        if self.sample_levels is not None:
            levels = self.sample_levels(level_key)
        obs, env_state = reset_batch(self.spec, self.env_params, levels, self.ppo.num_envs)
        return FusedCarry(train, RolloutCarry(env_state, obs, env_key), key)

    def iterate(self, carry: FusedCarry, levels: Level | None) -> tuple[FusedCarry, dict[str, Array]]:
        """One rollout of `ppo.num_steps` steps in every environment, then one PPO update."""
        key, level_key, update_key = jax.random.split(carry.key, 3)
        if self.sample_levels is not None:
            levels = self.sample_levels(level_key)
        envs, trajectory, stats = rollout(
            self.agent.act, carry.train.params, self.spec, self.env_params, carry.envs, levels, self.ppo.num_steps
        )
        # The parameters that acted are the ones trained, so the batch's version equals the learner's: lag 0.
        batch = make_batch(trajectory, envs.obs, carry.train.policy_version)
        train, losses = ppo_update(
            carry.train,
            batch,
            update_key,
            apply_fn=self.agent.apply,
            distribution=self.agent.distribution,
            optimizer=self.optimizer,
            config=self.ppo,
        )
        episodes = stats.episodes
        safe = jnp.maximum(episodes, 1)
        metrics = {
            **losses,
            "episodes": episodes,
            "solved": stats.solved,
            "failed": stats.failed,
            "timed_out": stats.timed_out,
            "nan_episodes": stats.nan,
            "return_sum": stats.return_sum,
            "length_sum": stats.length_sum,
            "solve_rate": jnp.where(episodes > 0, stats.solved / safe, jnp.nan),
            "episode_return": jnp.where(episodes > 0, stats.return_sum / safe, jnp.nan),
            "episode_length": jnp.where(episodes > 0, stats.length_sum / safe, jnp.nan),
            "reward_per_step": trajectory.reward.mean(),
        }
        return FusedCarry(train, envs, key), metrics

    def jitted(self) -> tuple[Callable[..., FusedCarry], Callable[..., tuple[FusedCarry, dict[str, Any]]]]:
        """(init, iterate) compiled; `iterate` donates its carry so the environments are updated in place."""
        return jax.jit(self.init), jax.jit(self.iterate, donate_argnums=0)
