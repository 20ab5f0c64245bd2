"""What every curriculum method is: the protocol its callers (the fused trainer, the curriculum service, the
commands) use, and the parts the methods share.

A method is a frozen dataclass of static parts (config, environment, batch size B, generator) whose methods are
pure and jittable: `init(key) -> state`, `sample(state, key, fresh) -> (state, batch)` and
`update(state, results) -> state`. What differs between methods is what `sample` hands out, what `update` does
with results, what needs scoring by whom, and a few defaults; those are the subclass's to say (`dr`, `plr`,
`accel`, `sfl` in this package), so no caller ever asks which method it holds. What it needs scored is one of two
things: the results of the episodes trained on (every method; `update`), or, where `batch_scored` is true,
candidates the caller plays with its current policy and hands to `refill`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp

from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.noop_filter import NoopFilterConfig, sample_filtered_levels
from impulse.curriculum.results import LevelResults
from impulse.curriculum.staging import Candidates
from impulse.curriculum.state import ORIGIN_NEW, CurriculumState, Knobs, LevelBatch, empty_state, knobs_from_config
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.generator import GeneratorConfig, sample_random_level
from impulse.engine.levels.level import LEVEL_ID_WORDS, Level

Array = jax.Array


@dataclass(frozen=True)
class Curriculum(ABC):
    """One curriculum method's static parts (config, environment, batch size B); its methods are pure and
    jittable. Subclasses say what `sample` and `update` do; `curriculum.methods.make_curriculum` picks the
    subclass that `config.method` names."""

    config: CurriculumConfig
    spec: EnvSpec
    env_params: EnvParams
    batch_size: int
    generator: GeneratorConfig = GeneratorConfig()

    method: ClassVar[str]
    """The method's name, as `curriculum.method` spells it (for logs and status lines)."""
    default_candidate_episodes: ClassVar[int] = 1
    """Finished episodes a candidate needs before it is scored when `curriculum.candidate_episodes` is None."""

    @property
    def batch_scored(self) -> bool:
        """Whether the buffer is rebuilt by `refill` from candidates the caller scores with its current policy
        (every `sfl_refresh_updates` policy versions, and before the first) rather than from training results."""
        return False

    def knobs(self, config: CurriculumConfig) -> Knobs:
        """The live knobs of `config` as state arrays, with this method's defaults where `config` leaves one
        open: what a state starts with, and what a live knob change puts into it."""
        return knobs_from_config(config, self.default_candidate_episodes)

    def init(self, key: Array) -> CurriculumState:
        """An empty curriculum (the example level only gives the shapes)."""
        example = sample_random_level(key, self.spec.sizes, self.generator)
        return empty_state(self.config, example, self.batch_size, self.knobs(self.config))

    def new_levels(self, key: Array, n: int) -> Level:
        """n fresh random levels, through the no-op filter unless it is off."""
        if self.config.noop_filter:
            filter_config = NoopFilterConfig(ratio=self.config.filter_ratio, num_steps=self.config.filter_steps)
            levels, _ = sample_filtered_levels(key, n, self.spec, self.env_params, self.generator, filter_config)
            return levels
        return self.random_levels(key, n)

    def random_levels(self, key: Array, n: int) -> Level:
        """n fresh random levels, unfiltered."""
        return jax.vmap(lambda k: sample_random_level(k, self.spec.sizes, self.generator))(jax.random.split(key, n))

    def fresh_levels(self, key: Array, fresh: Level | None) -> Level:
        """The B new levels a batch uses: `fresh` where the caller made them beforehand, else drawn here."""
        return self.new_levels(key, self.batch_size) if fresh is None else fresh

    def fresh_candidates(self, key: Array, fresh: Level | None) -> Candidates:
        """`fresh_levels` as candidates with no parent, ready to be staged."""
        b = self.batch_size
        return Candidates(self.fresh_levels(key, fresh), jnp.full(b, ORIGIN_NEW, jnp.int32),
                          jnp.zeros((b, LEVEL_ID_WORDS), jnp.uint32), jnp.zeros(b, jnp.int32))

    @abstractmethod
    def sample(self, state: CurriculumState, key: Array,
               fresh: Level | None = None) -> tuple[CurriculumState, LevelBatch]:
        """The next batch of B levels. `fresh`: B new levels made beforehand (the curriculum service makes them
        ahead, off its request path), used wherever the batch needs new ones; None draws them here. Whether the
        batch used them shows in `state.counters.new_batches`, which counts every batch that did."""

    @abstractmethod
    def update(self, state: CurriculumState, results: LevelResults) -> CurriculumState:
        """Learn from per-level results of played batches (any number of rows, in any order, from any mix of
        batches)."""

    def refill(self, state: CurriculumState, candidates: Level, solve_rate: Array,
               policy_version: Array) -> CurriculumState:
        """Rebuild the buffer from `candidates` [C] and each one's solve rate under the policy of
        `policy_version`; only for a method that is `batch_scored`."""
        raise NotImplementedError(f"curriculum {self.method} is not batch-scored: it has no refill")

    def insert(self, state: CurriculumState, level: Level) -> tuple[CurriculumState, Array]:
        """Put one given `level` (unbatched, of the curriculum's sizes: a level a person sends into a running
        curriculum) into the buffer: in an empty slot, else in place of the lowest-scored level, scored as high as
        the best buffered level so that replay picks it soon; from then on its results re-score it like any
        buffered level. Returns (state, the slot)."""
        buffer = state.buffer
        slot = jnp.where(buffer.filled.all(), jnp.argmin(jnp.where(buffer.filled, buffer.score, jnp.inf)),
                         jnp.argmin(buffer.filled))
        top = jnp.where(buffer.filled.any(), jnp.max(jnp.where(buffer.filled, buffer.score, -jnp.inf)), 0.0)
        version = jnp.max(jnp.where(buffer.filled, buffer.score_version, 0))
        clock = state.counters.clock
        buffer = buffer._replace(
            levels=jax.tree.map(lambda x, v: x.at[slot].set(v), buffer.levels, level),
            filled=buffer.filled.at[slot].set(True), score=buffer.score.at[slot].set(top),
            last_sampled=buffer.last_sampled.at[slot].set(clock), inserted_at=buffer.inserted_at.at[slot].set(clock),
            max_return=buffer.max_return.at[slot].set(0.0), episodes=buffer.episodes.at[slot].set(0.0),
            solved=buffer.solved.at[slot].set(0.0), score_version=buffer.score_version.at[slot].set(version),
            parent_id=buffer.parent_id.at[slot].set(0), generation=buffer.generation.at[slot].set(0),
            replays=buffer.replays.at[slot].set(0))
        counters = state.counters._replace(inserted=state.counters.inserted + 1,
                                           evicted=state.counters.evicted + state.buffer.filled[slot])
        return state._replace(buffer=buffer, counters=counters), slot


def buffer_ready(state: CurriculumState) -> Array:
    """Whether replay may start: the buffer holds a level and is at least `min_fill` full."""
    filled = state.buffer.filled
    return filled.any() & (filled.mean() >= state.knobs.min_fill)


def count_results(state: CurriculumState, results: LevelResults) -> CurriculumState:
    """`state` with `results` counted and otherwise unused: the update of a method whose buffer, if any, training
    results do not change."""
    counters = state.counters._replace(results=state.counters.results + results.valid.sum())
    return state._replace(counters=counters)
