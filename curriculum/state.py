"""The curriculum's state: a fixed-size level buffer, a staging area for candidates that are still being played,
the live knobs and a few counters, all as batched arrays, so the whole state is one pytree that jits, lives in
the fused trainer's carry and checkpoints with orbax as the `curriculum` item.

Slots and ids. The buffer has N slots and the staging area S; a slot is either filled (`filled` / `staged`) or
free. Levels are found by their 64-bit id (`Level.level_id`), never by slot: results from actors name ids, and a
slot can be reused while a level that used to sit in it is still being played.

Time. `clock` is the sampling counter of PLR's staleness term: it advances by one at every replay pick and at
every insertion attempt (as jaxued and Kinetix count it); a buffered level's `last_sampled` is the clock when it
was last picked or inserted, so its staleness is `clock - last_sampled`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.curriculum.config import PRIORITIZATIONS, SCORE_FUNCTIONS, CurriculumConfig
from impulse.engine.levels.level import LEVEL_ID_WORDS, Level

Array = jax.Array

ORIGIN_NEW, ORIGIN_REPLAY, ORIGIN_MUTATED = 0, 1, 2
ORIGIN_NAMES = ("new", "replay", "mutated")


class Knobs(NamedTuple):
    """The live knobs as arrays (see `curriculum.config.LIVE_KNOBS`); choices are indices into their lists."""

    score: Array  # int32 index into SCORE_FUNCTIONS
    prioritization: Array  # int32 index into PRIORITIZATIONS
    temperature: Array
    staleness_coef: Array
    replay_prob: Array
    min_fill: Array
    robust: Array  # bool
    num_edits: Array  # int32
    sfl_ratio: Array
    candidate_episodes: Array  # int32
    score_memory: Array


def knobs_from_config(config: CurriculumConfig, default_candidate_episodes: int) -> Knobs:
    """`config`'s live knobs as arrays. `default_candidate_episodes`: the method's own count, used where
    `config.candidate_episodes` is None (`Curriculum.default_candidate_episodes`; `Curriculum.knobs` passes it)."""
    episodes = default_candidate_episodes if config.candidate_episodes is None else config.candidate_episodes
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    i32 = lambda x: jnp.asarray(x, jnp.int32)  # noqa: E731
    return Knobs(
        score=i32(SCORE_FUNCTIONS.index(config.score)),
        prioritization=i32(PRIORITIZATIONS.index(config.prioritization)),
        temperature=f32(config.temperature),
        staleness_coef=f32(config.staleness_coef),
        replay_prob=f32(config.replay_prob),
        min_fill=f32(config.min_fill),
        robust=jnp.asarray(config.robust, bool),
        num_edits=i32(config.num_edits),
        sfl_ratio=f32(config.sfl_ratio),
        candidate_episodes=i32(episodes),
        score_memory=f32(config.score_memory),
    )


def config_with_knobs(config: CurriculumConfig, knobs: Knobs) -> CurriculumConfig:
    """`config` with its live knobs replaced by the values in `knobs` (host side): what a live service runs."""
    host = jax.device_get(knobs)
    return dataclasses.replace(
        config,
        score=SCORE_FUNCTIONS[int(host.score)],
        prioritization=PRIORITIZATIONS[int(host.prioritization)],
        temperature=round(float(host.temperature), 6),
        staleness_coef=round(float(host.staleness_coef), 6),
        replay_prob=round(float(host.replay_prob), 6),
        min_fill=round(float(host.min_fill), 6),
        robust=bool(host.robust),
        num_edits=int(host.num_edits),
        sfl_ratio=round(float(host.sfl_ratio), 6),
        candidate_episodes=int(host.candidate_episodes),
        score_memory=round(float(host.score_memory), 6),
    )


class Buffer(NamedTuple):
    """N scored levels (leaves [N])."""

    levels: Level
    filled: Array  # bool
    score: Array  # float32, the current score (meaningless where not filled)
    last_sampled: Array  # int32, clock at the last pick or the insertion
    inserted_at: Array  # int32, clock at the insertion
    max_return: Array  # float32, best episode return ever seen on the level (MaxMC)
    episodes: Array  # float32, finished episodes, decayed by score_memory at every new result
    solved: Array  # float32, solved episodes, decayed alike
    score_version: Array  # int32, policy version of the results behind the score
    parent_id: Array  # uint32 [N, 2], 0 unless the level is a mutated child
    generation: Array  # int32, mutations between the level and a generated ancestor
    replays: Array  # int32, times picked for replay


class Staging(NamedTuple):
    """S candidates (new or mutated levels) waiting for `candidate_episodes` finished episodes; leaves [S]. The
    result sums are `LevelResults`' fields, added up over every result received for the candidate."""

    levels: Level
    staged: Array  # bool
    staged_at: Array  # int32, clock when staged
    origin: Array  # int32, ORIGIN_NEW or ORIGIN_MUTATED
    parent_id: Array  # uint32 [S, 2]
    generation: Array  # int32
    handed: Array  # int32, batches the candidate was handed out in
    episodes: Array  # int32
    solved: Array  # int32
    return_max: Array  # float32
    value_sum: Array  # float32
    pvl_sum: Array  # float32
    l1_sum: Array  # float32
    policy_version: Array  # int32


class Counters(NamedTuple):
    """Totals since the start of the run (int32 scalars), for turnover and health metrics."""

    clock: Array
    inserted: Array  # candidates that entered the buffer
    evicted: Array  # buffered levels pushed out by a better candidate
    rejected: Array  # scored candidates that did not beat the level they would have replaced
    dropped_candidates: Array  # staged candidates overwritten before they were scored
    unknown_results: Array  # results for ids neither buffered nor staged (already scored and turned away, evicted)
    results: Array  # result rows applied
    new_batches: Array
    replay_batches: Array
    mutate_batches: Array


class CurriculumState(NamedTuple):
    buffer: Buffer
    staging: Staging
    counters: Counters
    knobs: Knobs
    parent_slots: Array  # int32 [B], buffer slots of the last replay batch (ACCEL mutates them next)
    mutate_next: Array  # bool, ACCEL: the next batch is the children of the last replay batch


class LevelBatch(NamedTuple):
    """What `sample` hands out: B levels, whether each is trained on, and where each came from."""

    levels: Level  # [B]
    train: Array  # bool [B]; false: only evaluated (robust PLR), its steps are masked out of the update
    origin: Array  # int32 [B], ORIGIN_*


def _repeat(level: Level, n: int) -> Level:
    return jax.tree.map(lambda x: jnp.zeros((n,) + x.shape, x.dtype), level)


def empty_state(config: CurriculumConfig, example: Level, batch_size: int, knobs: Knobs) -> CurriculumState:
    """An empty buffer and staging area shaped after one (unbatched) `example` level, with the live `knobs`."""
    n, s = config.buffer_size, config.staging_factor * batch_size
    i32 = lambda k: jnp.zeros(k, jnp.int32)  # noqa: E731
    f32 = lambda k: jnp.zeros(k, jnp.float32)  # noqa: E731
    ids = lambda k: jnp.zeros((k, LEVEL_ID_WORDS), jnp.uint32)  # noqa: E731
    zero = jnp.zeros((), jnp.int32)
    buffer = Buffer(_repeat(example, n), jnp.zeros(n, bool), f32(n), i32(n), i32(n), f32(n), f32(n), f32(n), i32(n),
                    ids(n), i32(n), i32(n))
    staging = Staging(_repeat(example, s), jnp.zeros(s, bool), i32(s), i32(s), ids(s), i32(s), i32(s), i32(s), i32(s),
                      f32(s), f32(s), f32(s), f32(s), i32(s))
    counters = Counters(*([zero] * len(Counters._fields)))
    return CurriculumState(buffer, staging, counters, knobs, i32(batch_size),
                           jnp.zeros((), bool))
