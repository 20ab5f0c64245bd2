"""The trajectory batch: the one type of experience that crosses from an actor to the learner.

Fused mode builds it inside its jitted loop and hands it straight to `learner.update.ppo_update`; an actor process
builds the same thing, the bus carries it as arrays, and the learner rebuilds it and calls the same update. The
contract, field by field:

- `steps`: [T, E] time-major transitions (`Trajectory`), including the id of the level every environment played at
  every step, so results are credited to levels by id and a curriculum can mask levels out of the gradient;
- `bootstrap_obs`: [E] the observation after the last step, which bootstraps the value targets;
- `behaviour_version`: the learner's policy version of the parameters that acted; the learner measures policy lag
  against it (0 in fused mode because the two versions are equal);
- `train_mask`: [T, E] which steps the update learns from (all of them, unless a curriculum marks levels that are
  only being evaluated);
- `actor_id`, `seq`: who produced the batch and its number in that actor's stream (fused mode: actor 0);
- `episodes`: what happened to the episodes that ended during the rollout (`EpisodeStats`), so that every mode
  reports the same episode metrics for the batch it trains on (`episode_metrics`).

Per-level results for the curriculum are computed from the steps by `curriculum.results.level_results`, keyed by
level id.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

Array = jax.Array


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
    episode_return: Array  # the finished episode's return on the step that ends it, 0 elsewhere
    level_id: Array  # [T, E, LEVEL_ID_WORDS] uint32: the level this step was played on


class EpisodeStats(NamedTuple):
    """Sums over the episodes that ended during a rollout (scalars): how many, how they ended, their returns and
    lengths."""

    episodes: Array
    solved: Array
    failed: Array
    timed_out: Array
    nan: Array
    return_sum: Array
    length_sum: Array


def no_episodes() -> EpisodeStats:
    """Stats of a rollout in which no episode ended."""
    return EpisodeStats(*(jnp.zeros((), dtype) for dtype in
                          (jnp.int32, jnp.int32, jnp.int32, jnp.int32, jnp.int32, jnp.float32, jnp.int32)))


def episode_metrics(stats: EpisodeStats) -> dict[str, Array]:
    """The episode metrics every mode reports per batch (metrics.jsonl, the progress line, the metrics window):
    the counts and sums, and solve rate, mean return and mean length (NaN when no episode ended). Works on device
    arrays inside a jitted function and on host values alike."""
    episodes = stats.episodes
    safe = jnp.maximum(episodes, 1)
    return {
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
    }


class TrajectoryBatch(NamedTuple):
    """What an actor sends and `ppo_update` consumes (see the module docstring)."""

    steps: Trajectory
    bootstrap_obs: Any
    behaviour_version: Array  # int32 scalar
    train_mask: Array  # bool [T, E]
    actor_id: Array  # int32 scalar
    seq: Array  # int32 scalar
    episodes: EpisodeStats  # scalars


def make_batch(
    steps: Trajectory,
    bootstrap_obs: Any,
    behaviour_version: Array | int,
    actor_id: Array | int = 0,
    seq: Array | int = 0,
    train_mask: Array | None = None,
    episodes: EpisodeStats | None = None,
) -> TrajectoryBatch:
    """A batch with every step trained on unless `train_mask` says otherwise, and the rollout's `episodes` (none
    ended, when not given). Jittable."""
    if train_mask is None:
        train_mask = jnp.ones(steps.reward.shape, bool)
    if episodes is None:
        episodes = no_episodes()
    return TrajectoryBatch(
        steps=steps,
        bootstrap_obs=bootstrap_obs,
        behaviour_version=jnp.asarray(behaviour_version, jnp.int32),
        train_mask=train_mask,
        actor_id=jnp.asarray(actor_id, jnp.int32),
        seq=jnp.asarray(seq, jnp.int32),
        episodes=episodes,
    )


def env_axes(batch: TrajectoryBatch) -> TrajectoryBatch:
    """The environment axis of every leaf of `batch` (None for the per-batch scalars), the axis a learner on
    several devices splits the batch along: 1 for the [T, E] steps and train mask, 0 for the [E] bootstrap
    observation."""
    return TrajectoryBatch(
        steps=jax.tree.map(lambda _: 1, batch.steps),
        bootstrap_obs=jax.tree.map(lambda _: 0, batch.bootstrap_obs),
        behaviour_version=None,
        train_mask=1,
        actor_id=None,
        seq=None,
        episodes=EpisodeStats(*(None for _ in EpisodeStats._fields)),
    )
