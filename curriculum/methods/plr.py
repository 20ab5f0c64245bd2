"""Prioritised level replay (PLR), and robust PLR (PLR-perp) under the live `robust` knob.

Once the buffer is `min_fill` full, a batch is replayed from it with probability `replay_prob` (levels picked by
score and staleness, `curriculum.priority`); otherwise the batch is new levels. New levels are staged and scored
once they have finished `candidate_episodes` episodes (`curriculum.staging`), then inserted if they beat the
buffered level with the lowest replay probability; replayed levels are re-scored in place by their new results
(`curriculum.methods.apply`). Under `robust` new levels are only evaluated: their batch entries say `train=False`,
so the learner trains on none of their steps and gradients come from replayed levels alone.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp

from impulse.curriculum.methods.apply import apply_results
from impulse.curriculum.methods.base import Curriculum, buffer_ready
from impulse.curriculum.priority import pick_replays
from impulse.curriculum.results import LevelResults
from impulse.curriculum.staging import take_candidates
from impulse.curriculum.state import ORIGIN_REPLAY, CurriculumState, LevelBatch
from impulse.engine.levels.level import Level

Array = jax.Array
Branch = Callable[[CurriculumState, Array], tuple[CurriculumState, LevelBatch]]
"""One kind of batch `sample` may hand out: (state, key) -> (state, batch)."""

NEW_BRANCH, REPLAY_BRANCH, MUTATE_BRANCH = 0, 1, 2
"""Positions in `PLR.branches`: new levels, a replay, the children of the last replay (ACCEL only)."""


@dataclass(frozen=True)
class PLR(Curriculum):
    """`curriculum.method="plr"`."""

    method = "plr"
    mutates: ClassVar[bool] = False
    """Whether every replay batch is followed by a batch of its mutated children (`MUTATE_BRANCH`)."""

    def branches(self, fresh: Level | None) -> tuple[Branch, ...]:
        """The kinds of batch `sample` chooses among, at the positions `NEW_BRANCH`, `REPLAY_BRANCH`, ..."""
        return functools.partial(self.new_batch, fresh=fresh), self.replay_batch

    def sample(self, state: CurriculumState, key: Array,
               fresh: Level | None = None) -> tuple[CurriculumState, LevelBatch]:
        coin_key, branch_key = jax.random.split(key)
        replay = buffer_ready(state) & (jax.random.uniform(coin_key) < state.knobs.replay_prob)
        branch = jnp.where(state.mutate_next, MUTATE_BRANCH, jnp.where(replay, REPLAY_BRANCH, NEW_BRANCH))
        return jax.lax.switch(branch, self.branches(fresh), state, branch_key)

    def level_batch(self, levels: Level, origin: Array | int, state: CurriculumState) -> LevelBatch:
        """`levels` handed out from `origin` (one for all or one each), only evaluated where `robust` asks it."""
        origin = jnp.broadcast_to(jnp.asarray(origin, jnp.int32), (self.batch_size,))
        evaluated_only = state.knobs.robust & (origin != ORIGIN_REPLAY)
        return LevelBatch(levels, ~evaluated_only, origin)

    def new_batch(self, state: CurriculumState, key: Array,
                  fresh: Level | None) -> tuple[CurriculumState, LevelBatch]:
        """Candidates still short of episodes (oldest first), then fresh levels, which are staged."""
        staging, counters, levels, origin = take_candidates(
            state.staging, state.counters, state.knobs, self.fresh_candidates(key, fresh),
            jnp.asarray(self.batch_size), rehand=True)
        counters = counters._replace(new_batches=counters.new_batches + 1)
        state = state._replace(staging=staging, counters=counters, mutate_next=jnp.zeros((), bool))
        return state, self.level_batch(levels, origin, state)

    def replay_batch(self, state: CurriculumState, key: Array) -> tuple[CurriculumState, LevelBatch]:
        """B buffered levels picked by the replay distribution; their slots are kept for the children of a
        method that `mutates`."""
        buffer, clock, slots = pick_replays(state.buffer, state.knobs, state.counters.clock, key, self.batch_size)
        counters = state.counters._replace(clock=clock, replay_batches=state.counters.replay_batches + 1)
        levels = jax.tree.map(lambda x: x[slots], buffer.levels)
        state = state._replace(buffer=buffer, counters=counters, parent_slots=slots.astype(jnp.int32),
                               mutate_next=jnp.asarray(self.mutates))
        return state, self.level_batch(levels, ORIGIN_REPLAY, state)

    def update(self, state: CurriculumState, results: LevelResults) -> CurriculumState:
        return apply_results(state, results, learnability_only=False)
