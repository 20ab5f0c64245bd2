"""Sampling for learnability (SFL), in two forms chosen by `curriculum.sfl_scoring`.

Both hand out batches whose `sfl_ratio` share is drawn uniformly from the buffer and whose rest are fresh levels,
all trained on; the buffer keeps the most learnable levels seen, learnability being p (1 - p) for a solve rate p
under the current policy, and a level never solved is not kept, even in a free slot.

- "online" (the default, a streaming form): the fresh part of each batch are candidates, scored from at least
  `candidate_episodes` episodes of training and each replacing the buffer's least learnable level if it beats it;
  buffered levels are re-scored whenever they are replayed, with `score_memory` forgetting old outcomes, so their
  scores age continuously. Replay starts once the buffer is `min_fill` full.
- "batch" (Kinetix's form, which rebuilds its buffer from dedicated evaluation rollouts every 128 updates): the
  caller, who holds the policy, plays `sfl_candidates` fresh levels `sfl_attempts` times every
  `sfl_refresh_updates` updates (and before the first), and `refill` makes the buffer the most learnable of them.
  Training results do not change the buffer, and replay starts with the first batch that finds it non-empty.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from impulse.curriculum.methods.apply import apply_results
from impulse.curriculum.methods.base import Curriculum, buffer_ready, count_results
from impulse.curriculum.priority import learnability
from impulse.curriculum.results import LevelResults
from impulse.curriculum.staging import row_mask, take_candidates
from impulse.curriculum.state import ORIGIN_NEW, ORIGIN_REPLAY, Buffer, CurriculumState, LevelBatch
from impulse.engine.levels.level import Level

Array = jax.Array


@dataclass(frozen=True)
class SFL(Curriculum):
    """`curriculum.method="sfl"`."""

    method = "sfl"
    default_candidate_episodes = 4  # a solve rate needs several episodes

    @property
    def batch_scored(self) -> bool:
        return self.config.sfl_scoring == "batch"

    def sample(self, state: CurriculumState, key: Array,
               fresh: Level | None = None) -> tuple[CurriculumState, LevelBatch]:
        pick_key, fresh_key = jax.random.split(key)
        b = self.batch_size
        can_replay = state.buffer.filled.any() if self.batch_scored else buffer_ready(state)
        from_buffer = jnp.where(can_replay, jnp.round(state.knobs.sfl_ratio * b).astype(jnp.int32), 0)
        buffer = state.buffer
        logits = jnp.where(buffer.filled, 0.0, -jnp.inf)
        slots = jax.random.categorical(pick_key, logits, shape=(b,))
        row = jnp.arange(b)
        picked = row < from_buffer
        replays = buffer.replays.at[jnp.where(picked, slots, buffer.replays.shape[0])].add(1, mode="drop")
        if self.batch_scored:  # fresh levels are only trained on; the next refill scores others
            staging, counters = state.staging, state.counters
            candidates, origin = self.fresh_levels(fresh_key, fresh), jnp.full(b, ORIGIN_NEW, jnp.int32)
        else:
            staging, counters, candidates, origin = take_candidates(
                state.staging, state.counters, state.knobs, self.fresh_candidates(fresh_key, fresh), b - from_buffer,
                rehand=True)
        candidate_row = jnp.clip(row - from_buffer, 0, b - 1)
        candidates = jax.tree.map(lambda x: x[candidate_row], candidates)
        replayed = jax.tree.map(lambda x: x[slots], buffer.levels)
        levels = jax.tree.map(lambda a, c: jnp.where(row_mask(picked, a), a, c), replayed, candidates)
        origin = jnp.where(picked, ORIGIN_REPLAY, origin[candidate_row])
        counters = counters._replace(new_batches=counters.new_batches + 1,
                                     replay_batches=counters.replay_batches + (from_buffer > 0))
        state = state._replace(buffer=buffer._replace(replays=replays), staging=staging, counters=counters)
        return state, LevelBatch(levels, jnp.ones(b, bool), origin)

    def update(self, state: CurriculumState, results: LevelResults) -> CurriculumState:
        """Online: results score candidates and re-score buffered levels, by learnability alone. Batch-scored:
        results are only counted; the buffer changes at the next `refill`."""
        if self.batch_scored:
            return count_results(state, results)
        return apply_results(state, results, learnability_only=True)

    def refill(self, state: CurriculumState, candidates: Level, solve_rate: Array,
               policy_version: Array) -> CurriculumState:
        """Batch-scored SFL: the buffer becomes the `buffer_size` most learnable of `candidates` [C], given each
        one's solve rate under the current policy (from `sfl_attempts` episodes). Learnability is scored as in
        the online form (`curriculum.priority.learnability`); a level never solved is not kept, as there, so the
        buffer may be left partly empty."""
        n = state.buffer.filled.shape[0]
        kept = min(n, solve_rate.shape[0])
        attempts = jnp.float32(self.config.sfl_attempts)
        score, picked = jax.lax.top_k(learnability(jnp.full_like(solve_rate, attempts), solve_rate * attempts), kept)

        def slots(values: Array, fill: float | bool = 0) -> Array:  # the kept rows, padded to the buffer's N slots
            padding = jnp.full((n - kept,) + values.shape[1:], fill, values.dtype)
            return jnp.concatenate([values, padding])

        filled = slots(score > 0, False)
        clock = state.counters.clock + 1
        old = state.buffer
        buffer = Buffer(
            levels=jax.tree.map(lambda x: slots(x[picked]), candidates),
            filled=filled,
            score=slots(score),
            last_sampled=jnp.full(n, clock, jnp.int32),
            inserted_at=jnp.full(n, clock, jnp.int32),
            max_return=jnp.zeros_like(old.max_return),
            episodes=jnp.where(filled, attempts, 0.0),
            solved=jnp.where(filled, slots(solve_rate[picked]) * attempts, 0.0),
            score_version=jnp.full(n, policy_version, jnp.int32),
            parent_id=jnp.zeros_like(old.parent_id),
            generation=jnp.zeros_like(old.generation),
            replays=jnp.zeros_like(old.replays),
        )
        counters = state.counters._replace(clock=clock, inserted=state.counters.inserted + filled.sum(),
                                           evicted=state.counters.evicted + old.filled.sum(),
                                           rejected=state.counters.rejected + (solve_rate.shape[0] - filled.sum()))
        return state._replace(buffer=buffer, counters=counters)
