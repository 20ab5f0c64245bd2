"""The curricula as pure functions: `init(key) -> state`, `sample(state, key) -> (state, batch)` and
`update(state, results) -> state`, the same jitted code inside `impulse train` and the curriculum service.

- **DR**: every batch is fresh random levels (through Kinetix's no-op filter unless it is off); no buffer.
- **PLR**: a batch is replayed from the buffer with probability `replay_prob` once the buffer is `min_fill`
  full, otherwise it is new levels. New levels are staged, scored once they have finished `candidate_episodes`
  episodes, and inserted if they beat the level with the lowest replay probability. Replayed levels are
  re-scored in place by their new results. With `robust` (PLR-perp) new levels are only evaluated: their batch
  entries say `train=False` and the learner trains on none of their steps.
- **ACCEL**: PLR whose every replay batch is followed by a batch of its children: each replayed level mutated by
  `num_edits` random edits, staged, scored and inserted like new levels (evaluated only under `robust`).
- **SFL**: a `sfl_ratio` share of every batch is drawn uniformly from the buffer, the rest are candidates whose
  learnability p (1 - p) is estimated from at least `candidate_episodes` episodes of the current policy; the
  buffer keeps the K most learnable levels seen (a candidate replaces the least learnable; one never solved is
  not kept, even in a free slot). Kinetix rebuilds its
  SFL buffer from scratch every 128 updates from dedicated evaluation rollouts; this streaming form scores the
  fresh half of each batch while training on it and re-scores buffered levels whenever they are replayed, with
  `score_memory` forgetting old outcomes, so its scores age continuously instead of in steps. With
  `sfl_scoring="batch"` it takes Kinetix's form instead: the caller, who holds the policy, scores
  `sfl_candidates` fresh levels every `sfl_refresh_updates` updates and `refill` makes the buffer the most
  learnable of them; replay starts at the first batch and training results do not change the buffer.

Scores, the replay distribution and eviction are in `curriculum.priority`; staging in `curriculum.staging`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.noop_filter import NoopFilterConfig, sample_filtered_levels
from impulse.curriculum.priority import LEARNABILITY, eviction_slot, learnability, pick_replays, score_of
from impulse.curriculum.results import LevelResults
from impulse.curriculum.staging import Candidates, add_result, find, take_candidates
from impulse.curriculum.state import (
    ORIGIN_MUTATED,
    ORIGIN_NEW,
    ORIGIN_REPLAY,
    Buffer,
    CurriculumState,
    LevelBatch,
    empty_state,
)
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.generator import GeneratorConfig, sample_random_level
from impulse.engine.levels.level import LEVEL_ID_WORDS, Level
from impulse.engine.levels.mutations import MutationConfig, mutate_level

Array = jax.Array

_NEW, _REPLAY, _MUTATE = 0, 1, 2


def _rows(mask: Array, like: Array) -> Array:
    return mask.reshape(mask.shape + (1,) * (like.ndim - 1))


def _select_rows(mask: Array, when_true: Level, when_false: Level) -> Level:
    return jax.tree.map(lambda a, b: jnp.where(_rows(mask, a), a, b), when_true, when_false)


@dataclass(frozen=True)
class Curriculum:
    """The static parts of a curriculum (config, environment, batch size B); its methods are pure and jittable."""

    config: CurriculumConfig
    spec: EnvSpec
    env_params: EnvParams
    batch_size: int
    generator: GeneratorConfig = GeneratorConfig()

    @functools.cached_property
    def mutation(self) -> MutationConfig:
        return MutationConfig(num_edits=self.config.max_edits, shapes=self.generator)

    @property
    def method(self) -> str:
        return self.config.method

    @property
    def batch_scored(self) -> bool:
        """SFL in Kinetix's form: the buffer is rebuilt by `refill` from levels the caller scored, not from the
        results of training episodes."""
        return self.method == "sfl" and self.config.sfl_scoring == "batch"

    def init(self, key: Array) -> CurriculumState:
        """An empty curriculum (the example level only gives the shapes)."""
        example = sample_random_level(key, self.spec.sizes, self.generator)
        return empty_state(self.config, example, self.batch_size)

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

    # -- sample ---------------------------------------------------------------------------------------------------

    def sample(self, state: CurriculumState, key: Array,
               fresh: Level | None = None) -> tuple[CurriculumState, LevelBatch]:
        """The next batch of B levels. `fresh`: B new levels made beforehand (the curriculum service makes them
        ahead, off its request path), used wherever the batch needs new ones; None draws them here. Whether the
        batch used them shows in `state.counters.new_batches`, which counts every batch that did."""
        if self.method == "dr":
            levels = self._new_levels(key, fresh)
            counters = state.counters._replace(new_batches=state.counters.new_batches + 1)
            return state._replace(counters=counters), self._batch(levels, ORIGIN_NEW, state)
        if self.method == "sfl":
            return self._sample_sfl(state, key, fresh)
        return self._sample_plr(state, key, fresh)

    def _new_levels(self, key: Array, fresh: Level | None) -> Level:
        return self.new_levels(key, self.batch_size) if fresh is None else fresh

    def _batch(self, levels: Level, origin: Array | int, state: CurriculumState) -> LevelBatch:
        origin = jnp.broadcast_to(jnp.asarray(origin, jnp.int32), (self.batch_size,))
        evaluated_only = state.knobs.robust & (origin != ORIGIN_REPLAY)
        train = jnp.ones(self.batch_size, bool) if self.method in ("dr", "sfl") else ~evaluated_only
        return LevelBatch(levels, train, origin)

    def _can_replay(self, state: CurriculumState) -> Array:
        filled = state.buffer.filled
        return filled.any() & (filled.mean() >= state.knobs.min_fill)

    def _fresh(self, key: Array, fresh: Level | None) -> Candidates:
        b = self.batch_size
        return Candidates(self._new_levels(key, fresh), jnp.full(b, ORIGIN_NEW, jnp.int32),
                          jnp.zeros((b, LEVEL_ID_WORDS), jnp.uint32), jnp.zeros(b, jnp.int32))

    def _sample_plr(self, state: CurriculumState, key: Array,
                    fresh: Level | None) -> tuple[CurriculumState, LevelBatch]:
        coin_key, branch_key = jax.random.split(key)
        replay = self._can_replay(state) & (jax.random.uniform(coin_key) < state.knobs.replay_prob)
        branches = (functools.partial(self._new_batch, fresh=fresh), self._replay_batch)
        if self.method == "accel":  # only ACCEL pays for compiling the mutation
            branches += (self._mutate_batch,)
        branch = jnp.where(state.mutate_next, _MUTATE, jnp.where(replay, _REPLAY, _NEW))
        return jax.lax.switch(branch, branches, state, branch_key)

    def _new_batch(self, state: CurriculumState, key: Array,
                   fresh: Level | None) -> tuple[CurriculumState, LevelBatch]:
        staging, counters, levels, origin = take_candidates(
            state.staging, state.counters, state.knobs, self._fresh(key, fresh), jnp.asarray(self.batch_size),
            rehand=True)
        counters = counters._replace(new_batches=counters.new_batches + 1)
        state = state._replace(staging=staging, counters=counters, mutate_next=jnp.zeros((), bool))
        return state, self._batch(levels, origin, state)

    def _replay_batch(self, state: CurriculumState, key: Array) -> tuple[CurriculumState, LevelBatch]:
        buffer, clock, slots = pick_replays(state.buffer, state.knobs, state.counters.clock, key, self.batch_size)
        counters = state.counters._replace(clock=clock, replay_batches=state.counters.replay_batches + 1)
        levels = jax.tree.map(lambda x: x[slots], buffer.levels)
        state = state._replace(buffer=buffer, counters=counters, parent_slots=slots.astype(jnp.int32),
                               mutate_next=jnp.asarray(self.method == "accel"))
        return state, self._batch(levels, ORIGIN_REPLAY, state)

    def _mutate_batch(self, state: CurriculumState, key: Array) -> tuple[CurriculumState, LevelBatch]:
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
        return state, self._batch(levels, origin, state)

    def _sample_sfl(self, state: CurriculumState, key: Array,
                    fresh: Level | None) -> tuple[CurriculumState, LevelBatch]:
        pick_key, fresh_key = jax.random.split(key)
        b = self.batch_size
        can_replay = state.buffer.filled.any() if self.batch_scored else self._can_replay(state)
        from_buffer = jnp.where(can_replay, jnp.round(state.knobs.sfl_ratio * b).astype(jnp.int32), 0)
        buffer = state.buffer
        logits = jnp.where(buffer.filled, 0.0, -jnp.inf)
        slots = jax.random.categorical(pick_key, logits, shape=(b,))
        row = jnp.arange(b)
        picked = row < from_buffer
        replays = buffer.replays.at[jnp.where(picked, slots, buffer.replays.shape[0])].add(1, mode="drop")
        if self.batch_scored:  # fresh levels are only trained on; the next refill scores others
            staging, counters = state.staging, state.counters
            candidates, origin = self._new_levels(fresh_key, fresh), jnp.full(b, ORIGIN_NEW, jnp.int32)
        else:
            staging, counters, candidates, origin = take_candidates(
                state.staging, state.counters, state.knobs, self._fresh(fresh_key, fresh), b - from_buffer,
                rehand=True)
        candidate_row = jnp.clip(row - from_buffer, 0, b - 1)
        candidates = jax.tree.map(lambda x: x[candidate_row], candidates)
        levels = _select_rows(picked, jax.tree.map(lambda x: x[slots], buffer.levels), candidates)
        origin = jnp.where(picked, ORIGIN_REPLAY, origin[candidate_row])
        counters = counters._replace(new_batches=counters.new_batches + 1,
                                     replay_batches=counters.replay_batches + (from_buffer > 0))
        state = state._replace(buffer=buffer._replace(replays=replays), staging=staging, counters=counters)
        return state, LevelBatch(levels, jnp.ones(b, bool), origin)

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

        def slots(values: Array, fill=0) -> Array:  # the kept rows, padded to the buffer's N slots
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

    # -- update ---------------------------------------------------------------------------------------------------

    def update(self, state: CurriculumState, results: LevelResults) -> CurriculumState:
        """Apply per-level results (any number of rows, in any order, from any mix of batches): buffered levels
        are re-scored, staged candidates accumulate and are offered to the buffer once played enough, results for
        unknown ids are counted and dropped.

        Rows are applied one after another (a row may re-score a level an earlier row put into the buffer), over
        the buffer's and staging area's bookkeeping and level ids only; the levels themselves, the bulk of the
        state, are copied into the buffer once at the end, each slot from the last candidate accepted into it."""
        if self.method == "dr" or self.batch_scored:
            counters = state.counters._replace(results=state.counters.results + results.valid.sum())
            return state._replace(counters=counters)
        by_score_only = self.method == "sfl"
        function = LEARNABILITY if by_score_only else state.knobs.score
        staged_ids = state.staging.levels.level_id
        no_slot = state.buffer.filled.shape[0]
        no_move = jnp.array([no_slot, 0], jnp.int32)  # (buffer slot, staging slot) of a row that moves no level

        def rescore(carry: _RowCarry, row: Array) -> tuple[_RowCarry, Array]:
            state, buffer_ids = carry
            buffer, knobs = state.buffer, state.knobs
            _, slot = find(buffer_ids, buffer.filled, results.level_id[row])
            memory = knobs.score_memory
            episodes = memory * buffer.episodes[slot] + results.episodes[row]
            solved = memory * buffer.solved[slot] + results.solved[row]
            max_return = jnp.maximum(buffer.max_return[slot], results.return_max[row])
            score = score_of(function, episodes, solved, max_return, results.value_sum[row], results.pvl_sum[row],
                             results.l1_sum[row], results.episodes[row])
            buffer = buffer._replace(
                episodes=buffer.episodes.at[slot].set(episodes),
                solved=buffer.solved.at[slot].set(solved),
                max_return=buffer.max_return.at[slot].set(max_return),
                score=buffer.score.at[slot].set(score),
                score_version=buffer.score_version.at[slot].set(results.policy_version[row]),
            )
            return _RowCarry(state._replace(buffer=buffer), buffer_ids), no_move

        def offer(carry: _RowCarry, slot: Array) -> tuple[_RowCarry, Array]:
            state, buffer_ids = carry
            staging, buffer, counters = state.staging, state.buffer, state.counters
            episodes, solved = staging.episodes[slot], staging.solved[slot]
            score = score_of(function, episodes.astype(jnp.float32), solved.astype(jnp.float32),
                             staging.return_max[slot], staging.value_sum[slot], staging.pvl_sum[slot],
                             staging.l1_sum[slot], episodes)
            clock = counters.clock + 1
            target = eviction_slot(buffer, state.knobs, clock, by_score_only)
            accept = ~buffer.filled[target] | (score > buffer.score[target])
            if by_score_only:  # SFL: a level the policy never solves (learnability 0) is not worth a slot
                accept = accept & (score > 0)
            index = jnp.where(accept, target, no_slot)

            def put(old: Array, new) -> Array:
                return old.at[index].set(new, mode="drop")

            buffer = buffer._replace(
                filled=put(buffer.filled, True),
                score=put(buffer.score, score),
                last_sampled=put(buffer.last_sampled, clock),
                inserted_at=put(buffer.inserted_at, clock),
                max_return=put(buffer.max_return, staging.return_max[slot]),
                episodes=put(buffer.episodes, episodes.astype(jnp.float32)),
                solved=put(buffer.solved, solved.astype(jnp.float32)),
                score_version=put(buffer.score_version, staging.policy_version[slot]),
                parent_id=put(buffer.parent_id, staging.parent_id[slot]),
                generation=put(buffer.generation, staging.generation[slot]),
                replays=put(buffer.replays, 0),
            )
            counters = counters._replace(
                clock=clock,
                inserted=counters.inserted + accept,
                evicted=counters.evicted + (accept & state.buffer.filled[target]),
                rejected=counters.rejected + ~accept,
            )
            staging = staging._replace(staged=staging.staged.at[slot].set(False))
            state = state._replace(buffer=buffer, staging=staging, counters=counters)
            return _RowCarry(state, put(buffer_ids, staged_ids[slot])), jnp.stack([index, slot]).astype(jnp.int32)

        def accumulate(carry: _RowCarry, row: Array) -> tuple[_RowCarry, Array]:
            state, buffer_ids = carry
            _, slot = find(staged_ids, state.staging.staged, results.level_id[row])
            state = state._replace(staging=add_result(state.staging, slot, results, row))
            ready = state.staging.episodes[slot] >= state.knobs.candidate_episodes
            return jax.lax.cond(ready, offer, lambda c, _: (c, no_move), _RowCarry(state, buffer_ids), slot)

        def unknown(carry: _RowCarry, row: Array) -> tuple[_RowCarry, Array]:
            state = carry.state
            counters = state.counters._replace(unknown_results=state.counters.unknown_results + 1)
            return carry._replace(state=state._replace(counters=counters)), no_move

        def skip(carry: _RowCarry, row: Array) -> tuple[_RowCarry, Array]:
            return carry, no_move

        def apply_row(carry: _RowCarry, row: Array) -> tuple[_RowCarry, Array]:
            level_id = results.level_id[row]
            buffered, _ = find(carry.buffer_ids, carry.state.buffer.filled, level_id)
            staged, _ = find(staged_ids, carry.state.staging.staged, level_id)
            valid = results.valid[row] & (results.episodes[row] > 0)
            case = jnp.where(~valid, 0, jnp.where(buffered, 1, jnp.where(staged, 2, 3)))
            return jax.lax.switch(case, (skip, rescore, accumulate, unknown), carry, row)

        slim = state._replace(buffer=state.buffer._replace(levels=None), staging=state.staging._replace(levels=None))
        carry, moves = jax.lax.scan(apply_row, _RowCarry(slim, state.buffer.levels.level_id),
                                    jnp.arange(results.valid.shape[0]))
        levels = _move_levels(state.buffer.levels, state.staging.levels, into=moves[:, 0], source=moves[:, 1])
        state = carry.state._replace(buffer=carry.state.buffer._replace(levels=levels),
                                     staging=carry.state.staging._replace(levels=state.staging.levels))
        counters = state.counters._replace(results=state.counters.results + results.valid.sum())
        return state._replace(counters=counters)


class _RowCarry(NamedTuple):
    """What `Curriculum.update` carries from row to row: the state without its levels, and the buffer's level ids
    (which change as candidates move in)."""

    state: CurriculumState
    buffer_ids: Array  # uint32 [N, LEVEL_ID_WORDS]


def _move_levels(buffered: Level, staged: Level, into: Array, source: Array) -> Level:
    """The buffer's levels after `Curriculum.update`'s moves: row r put staging slot `source[r]` into buffer slot
    `into[r]` (`into` past the buffer's last slot: no move). Where several rows moved into one slot, the last
    one's level stays, as if each had been copied in turn."""
    size = buffered.level_id.shape[0]
    rows = jnp.arange(into.shape[0])
    last = jnp.full(size, -1, jnp.int32).at[into].max(rows, mode="drop")
    replaced = last >= 0
    taken = source[jnp.maximum(last, 0)]
    return jax.tree.map(lambda old, new: jnp.where(_rows(replaced, old), new[taken], old), buffered, staged)
