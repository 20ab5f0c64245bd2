"""The staging area: where new and mutated levels wait until they have been played enough to be scored.

A candidate is handed out in a batch, played (by the fused trainer or by actors, maybe several at once), and its
results add up here by level id. Once it has `candidate_episodes` finished episodes it is scored and offered to
the buffer, and its staging slot is freed. A candidate that has not yet been played enough is handed out again,
oldest first, ahead of fresh levels; when the area is full the oldest unscored candidate not in the current
batch makes room (counted as dropped). All of it is index plumbing over fixed-size arrays, kept here.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.curriculum.results import LevelResults
from impulse.curriculum.state import Counters, Knobs, Staging
from impulse.engine.levels.level import Level

Array = jax.Array

_NEVER = -(2**30)
_FREE = 2**30


class Candidates(NamedTuple):
    """Freshly made candidates (a batch of B levels with their lineage), before they are staged."""

    levels: Level
    origin: Array  # int32 [B]
    parent_id: Array  # uint32 [B, 2]
    generation: Array  # int32 [B]


def take_candidates(
    staging: Staging,
    counters: Counters,
    knobs: Knobs,
    fresh: Candidates,
    num_used: Array,
    rehand: bool,
) -> tuple[Staging, Counters, Level, Array]:
    """The first `num_used` of B candidate rows for a batch: pending candidates first (oldest first, only if
    `rehand`), then fresh ones, which are staged. Returns (staging, counters, levels [B], origin [B]); rows at
    and after `num_used` hold fresh levels that were not staged (the caller does not use them)."""
    size = staging.staged.shape[0]
    batch = fresh.origin.shape[0]
    clock = counters.clock
    pending = staging.staged & (staging.episodes < knobs.candidate_episodes)
    age = jnp.where(pending, clock - staging.staged_at, _NEVER)
    _, oldest = jax.lax.top_k(age, batch)
    row = jnp.arange(batch)
    num_handed = jnp.minimum(pending.sum(), num_used) if rehand else jnp.zeros((), jnp.int32)
    handed = row < num_handed
    handed_slot = jnp.where(handed, oldest, size)
    in_batch = jnp.zeros(size, bool).at[handed_slot].set(True, mode="drop")

    room = jnp.where(~staging.staged, _FREE, jnp.where(in_batch, _NEVER, clock - staging.staged_at))
    _, writable = jax.lax.top_k(room, batch)
    fresh_row = jnp.clip(row - num_handed, 0, batch - 1)
    is_fresh = ~handed & (row < num_used)
    write_slot = jnp.where(is_fresh, writable[fresh_row], size)
    overwritten = jnp.zeros(size, bool).at[write_slot].set(True, mode="drop") & staging.staged

    take = lambda x: x[fresh_row]  # noqa: E731
    fresh_levels = jax.tree.map(take, fresh.levels)
    levels = jax.tree.map(lambda old, new: jnp.where(row_mask(handed, old), old, new),
                          jax.tree.map(lambda x: x[jnp.minimum(handed_slot, size - 1)], staging.levels),
                          fresh_levels)
    origin = jnp.where(handed, staging.origin[jnp.minimum(handed_slot, size - 1)], take(fresh.origin))

    def put(old: Array, new: Array) -> Array:
        return old.at[write_slot].set(new, mode="drop")

    zeros_i = jnp.zeros(batch, jnp.int32)
    zeros_f = jnp.zeros(batch, jnp.float32)
    staging = Staging(
        levels=jax.tree.map(put, staging.levels, fresh_levels),
        staged=put(staging.staged, jnp.ones(batch, bool)),
        staged_at=put(staging.staged_at, jnp.full(batch, clock)),
        origin=put(staging.origin, take(fresh.origin)),
        parent_id=put(staging.parent_id, take(fresh.parent_id)),
        generation=put(staging.generation, take(fresh.generation)),
        handed=put(staging.handed, jnp.ones(batch, jnp.int32)).at[handed_slot].add(1, mode="drop"),
        episodes=put(staging.episodes, zeros_i),
        solved=put(staging.solved, zeros_i),
        return_max=put(staging.return_max, jnp.full(batch, -jnp.inf)),
        value_sum=put(staging.value_sum, zeros_f),
        pvl_sum=put(staging.pvl_sum, zeros_f),
        l1_sum=put(staging.l1_sum, zeros_f),
        policy_version=put(staging.policy_version, zeros_i),
    )
    counters = counters._replace(dropped_candidates=counters.dropped_candidates + overwritten.sum())
    return staging, counters, levels, origin


def row_mask(mask: Array, like: Array) -> Array:
    """`mask` [R] shaped to broadcast against `like` [R, ...] (one value per row), for a `jnp.where` that picks
    whole rows of a batched leaf."""
    return mask.reshape(mask.shape + (1,) * (like.ndim - 1))


def add_result(staging: Staging, slot: Array, results: LevelResults, row: Array) -> Staging:
    """Add result row `row` to the candidate in `slot`."""
    return staging._replace(
        episodes=staging.episodes.at[slot].add(results.episodes[row]),
        solved=staging.solved.at[slot].add(results.solved[row]),
        return_max=staging.return_max.at[slot].max(results.return_max[row]),
        value_sum=staging.value_sum.at[slot].add(results.value_sum[row]),
        pvl_sum=staging.pvl_sum.at[slot].add(results.pvl_sum[row]),
        l1_sum=staging.l1_sum.at[slot].add(results.l1_sum[row]),
        policy_version=staging.policy_version.at[slot].set(results.policy_version[row]),
    )


def find(ids: Array, present: Array, level_id: Array) -> tuple[Array, Array]:
    """(whether `level_id` is among the present `ids` [M, 2], its slot)."""
    match = present & jnp.all(ids == level_id, axis=-1)
    return match.any(), jnp.argmax(match)
