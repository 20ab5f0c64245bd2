"""What the side that played levels tells the curriculum: per-level results with the score inputs that need the
policy's values (MaxMC, positive and absolute GAE), computed from a trajectory batch.

The fused trainer calls this inside its jitted iteration and an actor process before it publishes, so the two
report exactly the same thing. Advantages are plain GAE over the behaviour policy's own values (as jaxued and
Kinetix score levels), bootstrapped with the value of the batch's last observation.
"""

from __future__ import annotations

from typing import Any

import jax

from impulse.actors.trajectory import TrajectoryBatch
from impulse.curriculum.results import LevelResults, level_results
from impulse.learner.agent import Agent
from impulse.learner.config import PPOConfig
from impulse.learner.returns import gae

Array = jax.Array


def batch_level_results(agent: Agent, ppo: PPOConfig, params: Any, batch: TrajectoryBatch, rows: int) -> LevelResults:
    """Per-level results of `batch` (played by `params`) in `rows` rows (at least E + K for K levels). With `agent`
    and `ppo` bound, this is an actor's `actors.process.LevelResultsFn`."""
    steps = batch.steps
    _, bootstrap_value = agent.apply(params, batch.bootstrap_obs)
    discounts = ppo.gamma * (1.0 - steps.done.astype(steps.value.dtype))
    _, advantages = gae(steps.reward, steps.value, bootstrap_value, discounts, ppo.gae_lambda)
    return level_results(steps.level_id, steps.done, steps.solved, steps.episode_return, steps.value, advantages,
                         batch.behaviour_version, rows)
