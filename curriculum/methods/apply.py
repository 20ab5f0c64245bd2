"""Results applied to a buffer and staging area, row by row: the `update` of every method that scores levels from
the episodes trained on (PLR, ACCEL, online SFL).

A row for a buffered level re-scores it in place; a row for a staged candidate adds to its sums and, once the
candidate has `candidate_episodes` finished episodes, scores it and offers it to the buffer; a row for an id
neither buffered nor staged is counted and dropped. Rows are applied one after another (a row may re-score a level
an earlier row put into the buffer), over the buffer's and staging area's bookkeeping and level ids only; the
levels themselves, the bulk of the state, are copied into the buffer once at the end, each slot from the last
candidate accepted into it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.curriculum.methods.base import count_results
from impulse.curriculum.priority import LEARNABILITY, eviction_slot, score_of
from impulse.curriculum.results import LevelResults
from impulse.curriculum.staging import add_result, find, row_mask
from impulse.curriculum.state import CurriculumState
from impulse.engine.levels.level import Level

Array = jax.Array


class _RowCarry(NamedTuple):
    """What `apply_results` carries from row to row: the state without its levels, and the buffer's level ids
    (which change as candidates move in)."""

    state: CurriculumState
    buffer_ids: Array  # uint32 [N, LEVEL_ID_WORDS]


def apply_results(state: CurriculumState, results: LevelResults, learnability_only: bool) -> CurriculumState:
    """`state` after `results` (see the module docstring). Levels are scored by the live `score` knob, or, with
    `learnability_only` (SFL), always by learnability, in which case a candidate competes with the buffer's
    lowest-scored level (not its least likely replay) and one whose learnability is 0 is never kept."""
    function = LEARNABILITY if learnability_only else state.knobs.score
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
        target = eviction_slot(buffer, state.knobs, clock, learnability_only)
        accept = ~buffer.filled[target] | (score > buffer.score[target])
        if learnability_only:  # a level the policy never solves (learnability 0) is not worth a slot
            accept = accept & (score > 0)
        index = jnp.where(accept, target, no_slot)

        def put(old: Array, new: Array | float | bool | int) -> Array:
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
    return count_results(state, results)


def _move_levels(buffered: Level, staged: Level, into: Array, source: Array) -> Level:
    """The buffer's levels after `apply_results`' moves: row r put staging slot `source[r]` into buffer slot
    `into[r]` (`into` past the buffer's last slot: no move). Where several rows moved into one slot, the last
    one's level stays, as if each had been copied in turn."""
    size = buffered.level_id.shape[0]
    rows = jnp.arange(into.shape[0])
    last = jnp.full(size, -1, jnp.int32).at[into].max(rows, mode="drop")
    replaced = last >= 0
    taken = source[jnp.maximum(last, 0)]
    return jax.tree.map(lambda old, new: jnp.where(row_mask(replaced, old), new[taken], old), buffered, staged)
