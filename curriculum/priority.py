"""Scores and the replay distribution: how results become a level's score, and scores and staleness become the
probability of replaying it (PLR, Jiang et al. 2021, as jaxued and Kinetix implement it).

- Score functions, from one level's result sums over E finished episodes: MaxMC = R_max - mean V (R_max the best
  return ever seen on the level), PVL = mean max(A, 0), L1 value loss = mean |A| (per-episode means, averaged
  over episodes), learnability = p (1 - p) + 0.001 p with p the solve rate (the small term prefers the more
  solvable of two levels equally learnable, as Kinetix's SFL does).
- Replay distribution over filled slots: P = (1 - rho) P_S + rho P_C, with P_S from scores by rank (h = 1/rank)
  or power (h = max(score, 0)), as h^(1/beta) normalised, and P_C proportional to staleness (clock minus the
  clock at the last pick). Either part falls back to uniform over filled slots when all its weights are 0.
- Eviction: a candidate replaces the slot with the lowest replay probability (PLR, ACCEL) or the lowest score
  (SFL, which keeps the top K), and only if its score is strictly higher; a free slot takes any candidate.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from impulse.curriculum.state import Buffer, Knobs

Array = jax.Array

LEARNABILITY = 3  # index of "learnability" in curriculum.config.SCORE_FUNCTIONS
SOLVABILITY_TIE_BREAK = 0.001


def learnability(episodes: Array, solved: Array) -> Array:
    """p (1 - p) + 0.001 p for the solve rate p = solved / episodes (0 without episodes)."""
    p = solved / jnp.maximum(episodes, 1e-6)
    return jnp.where(episodes > 0, p * (1.0 - p) + SOLVABILITY_TIE_BREAK * p, 0.0)


def score_of(function: Array, episodes: Array, solved: Array, max_return: Array, value_sum: Array,
             pvl_sum: Array, l1_sum: Array, window_episodes: Array) -> Array:
    """The score chosen by `function` (an index into SCORE_FUNCTIONS). `episodes`/`solved` are the counts the
    solve rate comes from; the value-based sums are over the `window_episodes` of the newest results."""
    per_episode = 1.0 / jnp.maximum(window_episodes, 1).astype(jnp.float32)
    scores = jnp.stack([
        max_return - value_sum * per_episode,
        pvl_sum * per_episode,
        l1_sum * per_episode,
        learnability(episodes, solved),
    ])
    return scores[function]


def _normalised_or_uniform(weights: Array, filled: Array) -> Array:
    total = weights.sum()
    uniform = filled / jnp.maximum(filled.sum(), 1)
    return jnp.where(total > 0, weights / jnp.where(total > 0, total, 1.0), uniform)


def score_weights(buffer: Buffer, knobs: Knobs) -> Array:
    """P_S over the N slots (0 where not filled)."""
    filled = buffer.filled
    masked = jnp.where(filled, buffer.score, -jnp.inf)
    order = jnp.argsort(-masked, stable=True)
    rank = jnp.zeros_like(order).at[order].set(jnp.arange(1, order.shape[0] + 1, dtype=order.dtype))
    by_rank = 1.0 / rank.astype(jnp.float32)
    by_power = jnp.maximum(buffer.score, 0.0)
    h = jnp.where(knobs.prioritization == 0, by_rank, by_power)
    h = jnp.where(filled, h ** (1.0 / knobs.temperature), 0.0)
    return _normalised_or_uniform(h, filled)


def staleness_weights(buffer: Buffer, clock: Array) -> Array:
    """P_C over the N slots (0 where not filled)."""
    stale = jnp.where(buffer.filled, clock - buffer.last_sampled, 0).astype(jnp.float32)
    return _normalised_or_uniform(stale, buffer.filled)


def replay_distribution(buffer: Buffer, knobs: Knobs, clock: Array, by_score: Array | None = None) -> Array:
    """P_replay over the N slots; `by_score` passes a P_S already computed (scores unchanged since)."""
    by_score = score_weights(buffer, knobs) if by_score is None else by_score
    rho = knobs.staleness_coef
    return (1.0 - rho) * by_score + rho * staleness_weights(buffer, clock)


def pick_replays(buffer: Buffer, knobs: Knobs, clock: Array, key: Array, n: int) -> tuple[Buffer, Array, Array]:
    """n sequential picks with replacement from P_replay, each advancing the clock and resetting the picked
    level's staleness before the next pick (jaxued's order). Returns (buffer, clock, slots [n])."""
    by_score = score_weights(buffer, knobs)

    def pick(carry, pick_key):
        last_sampled, replays, clock = carry
        current = buffer._replace(last_sampled=last_sampled)
        p = replay_distribution(current, knobs, clock, by_score)
        slot = jax.random.choice(pick_key, p.shape[0], p=p)
        clock = clock + 1
        return (last_sampled.at[slot].set(clock), replays.at[slot].add(1), clock), slot

    (last_sampled, replays, clock), slots = jax.lax.scan(
        pick, (buffer.last_sampled, buffer.replays, clock), jax.random.split(key, n))
    return buffer._replace(last_sampled=last_sampled, replays=replays), clock, slots


def eviction_slot(buffer: Buffer, knobs: Knobs, clock: Array, by_score_only: bool) -> Array:
    """The slot a new candidate competes for: the first free one, else the lowest replay probability (or the
    lowest score when `by_score_only`)."""
    free = ~buffer.filled
    lowest = buffer.score if by_score_only else replay_distribution(buffer, knobs, clock)
    target = jnp.argmin(jnp.where(buffer.filled, lowest, jnp.inf))
    return jnp.where(free.any(), jnp.argmax(free), target)
