"""ACCEL: PLR whose every replay batch is followed by a batch of its children, each replayed level changed by
`num_edits` random edits (`engine.levels.mutations`). Children are staged, scored and inserted like new levels,
with their parent and generation recorded, and are only evaluated under `robust`, like new levels.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from impulse.curriculum.methods.plr import PLR, Branch
from impulse.curriculum.staging import Candidates, take_candidates
from impulse.curriculum.state import ORIGIN_MUTATED, CurriculumState, LevelBatch
from impulse.engine.levels.level import Level
from impulse.engine.levels.mutations import MutationConfig, mutate_level

Array = jax.Array


@dataclass(frozen=True)
class ACCEL(PLR):
    """`curriculum.method="accel"`."""

    method = "accel"
    mutates = True

    @functools.cached_property
    def mutation(self) -> MutationConfig:
        """The mutation's static bounds: at most `max_edits` edits, shapes as the generator makes them."""
        return MutationConfig(num_edits=self.config.max_edits, shapes=self.generator)

    def branches(self, fresh: Level | None) -> tuple[Branch, ...]:
        return super().branches(fresh) + (self.mutate_batch,)  # only ACCEL pays for compiling the mutation

    def mutate_batch(self, state: CurriculumState, key: Array) -> tuple[CurriculumState, LevelBatch]:
        """The children of the last replay batch's levels (`state.parent_slots`), staged as candidates."""
        buffer, slots = state.buffer, state.parent_slots
        parents = jax.tree.map(lambda x: x[slots], buffer.levels)
        keys = jax.random.split(key, self.batch_size)
        mutate = lambda k, lv: mutate_level(k, lv, self.spec.sizes, self.mutation, state.knobs.num_edits)  # noqa: E731
        children = Candidates(jax.vmap(mutate)(keys, parents), jnp.full(self.batch_size, ORIGIN_MUTATED, jnp.int32),
                              buffer.levels.level_id[slots], buffer.generation[slots] + 1)
        staging, counters, levels, origin = take_candidates(
            state.staging, state.counters, state.knobs, children, jnp.asarray(self.batch_size), rehand=False)
        counters = counters._replace(mutate_batches=counters.mutate_batches + 1)
        state = state._replace(staging=staging, counters=counters, mutate_next=jnp.zeros((), bool))
        return state, self.level_batch(levels, origin, state)
