"""Domain randomisation: every batch is B fresh random levels (through Kinetix's no-op filter unless it is off),
all trained on. It keeps no buffer: results are only counted, and nothing is scored.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from impulse.curriculum.methods.base import Curriculum, count_results
from impulse.curriculum.results import LevelResults
from impulse.curriculum.state import ORIGIN_NEW, CurriculumState, LevelBatch
from impulse.engine.levels.level import Level

Array = jax.Array


@dataclass(frozen=True)
class DomainRandomisation(Curriculum):
    """`curriculum.method="dr"`."""

    method = "dr"

    def sample(self, state: CurriculumState, key: Array,
               fresh: Level | None = None) -> tuple[CurriculumState, LevelBatch]:
        b = self.batch_size
        batch = LevelBatch(self.fresh_levels(key, fresh), jnp.ones(b, bool), jnp.full(b, ORIGIN_NEW, jnp.int32))
        counters = state.counters._replace(new_batches=state.counters.new_batches + 1)
        return state._replace(counters=counters), batch

    def update(self, state: CurriculumState, results: LevelResults) -> CurriculumState:
        return count_results(state, results)
