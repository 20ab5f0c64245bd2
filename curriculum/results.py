"""Per-level results: what the side that plays levels reports to the curriculum, keyed by level id.

A rollout's steps are tallied per finished episode, then per level id, into a fixed number of rows (so the same
function runs jitted inside the fused trainer and in an actor before it publishes). Every quantity a score
function needs is reported as a sum over the level's finished episodes, so results from several rollouts (or
several actors) add up, and the curriculum turns sums into means when it scores:

- `episodes`, `solved`: finished episodes and how many ended with green touching blue (the solve rate p);
- `return_sum`, `return_max`: their undiscounted returns (MaxMC needs the best return ever seen on a level);
- `value_sum`, `pvl_sum`, `l1_sum`: per episode, the mean over its steps of the behaviour value V(s_t), of
  max(A_t, 0) and of |A_t| (A: the behaviour rollout's GAE advantages), summed over episodes;
- `policy_version`: the policy that played, so the curriculum knows how old a score is.

An episode that began before the rollout window contributes the steps inside it (the window is all a rollout
sees); its outcome and return are exact, since the environment tracks them across windows.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.levels.level import LEVEL_ID_WORDS

Array = jax.Array

_NO_LEVEL = np.uint32(0xFFFFFFFF)  # sorts after every real id word


class LevelResults(NamedTuple):
    """Results for up to R levels (leaves [R], ids [R, LEVEL_ID_WORDS]); rows with `valid` false are padding."""

    level_id: Array  # uint32 [R, 2]
    valid: Array  # bool
    episodes: Array  # int32
    solved: Array  # int32
    return_sum: Array  # float32
    return_max: Array  # float32
    value_sum: Array  # float32
    pvl_sum: Array  # float32
    l1_sum: Array  # float32
    policy_version: Array  # int32


RESULT_FIELDS: tuple[str, ...] = LevelResults._fields


def empty_results(rows: int) -> LevelResults:
    """R rows of padding."""
    zeros_i = jnp.zeros(rows, jnp.int32)
    zeros_f = jnp.zeros(rows, jnp.float32)
    return LevelResults(
        level_id=jnp.zeros((rows, LEVEL_ID_WORDS), jnp.uint32),
        valid=jnp.zeros(rows, bool),
        episodes=zeros_i,
        solved=zeros_i,
        return_sum=zeros_f,
        return_max=zeros_f,
        value_sum=zeros_f,
        pvl_sum=zeros_f,
        l1_sum=zeros_f,
        policy_version=zeros_i,
    )


class _Episode(NamedTuple):
    """Per-environment running sums over the current episode's steps inside the window."""

    steps: Array
    value: Array
    positive_advantage: Array
    absolute_advantage: Array


def _episode_means(value: Array, advantage: Array, done: Array) -> tuple[Array, Array, Array]:
    """[T, E] per-step means of V, max(A, 0) and |A| over the episode that ends at each step (0 elsewhere)."""

    def one_step(running: _Episode, inputs):
        v, a, d = inputs
        running = _Episode(running.steps + 1, running.value + v, running.positive_advantage + jnp.maximum(a, 0.0),
                           running.absolute_advantage + jnp.abs(a))
        n = running.steps.astype(jnp.float32)
        means = (jnp.where(d, running.value / n, 0.0), jnp.where(d, running.positive_advantage / n, 0.0),
                 jnp.where(d, running.absolute_advantage / n, 0.0))
        running = jax.tree.map(lambda x: jnp.where(d, jnp.zeros_like(x), x), running)
        return running, means

    zeros = jnp.zeros(value.shape[1:], jnp.float32)
    start = _Episode(jnp.zeros(value.shape[1:], jnp.int32), zeros, zeros, zeros)
    _, means = jax.lax.scan(one_step, start, (value, advantage, done))
    return means


def level_results(
    level_id: Array,
    done: Array,
    solved: Array,
    episode_return: Array,
    value: Array,
    advantage: Array,
    policy_version: Array | int,
    rows: int,
) -> LevelResults:
    """Tally the episodes that ended in a [T, E] window by level id into `rows` rows (jittable; `rows` static).

    `level_id` [T, E, 2] is the level each step was played on, `done`/`solved` flag the step that ends an episode
    (and whether it was solved), `episode_return` is the finished episode's return on that step, `value` and
    `advantage` are the behaviour policy's values and GAE advantages. A window of E environments on a batch of K
    levels touches at most E + K levels, which is enough rows; levels beyond `rows` are left out.
    """
    done = done.astype(bool)
    value_mean, pvl, l1 = _episode_means(value.astype(jnp.float32), advantage.astype(jnp.float32), done)
    flat = lambda x: x.reshape((-1,) + x.shape[2:])  # noqa: E731
    ids = jnp.where(flat(done)[:, None], flat(level_id), _NO_LEVEL)
    order = jnp.lexsort((ids[:, 1], ids[:, 0]))
    ids = ids[order]
    ended = flat(done)[order]
    starts = jnp.concatenate([jnp.ones(1, bool), jnp.any(ids[1:] != ids[:-1], axis=-1)])
    segment = jnp.cumsum(starts) - 1

    def total(x: Array) -> Array:
        return jax.ops.segment_sum(flat(x)[order] * ended, segment, num_segments=rows, indices_are_sorted=True)

    episodes = total(done.astype(jnp.int32))
    returns = jnp.where(done, episode_return, -jnp.inf)
    return_max = jax.ops.segment_max(flat(returns)[order], segment, num_segments=rows, indices_are_sorted=True)
    row_id = jnp.zeros((rows, LEVEL_ID_WORDS), jnp.uint32).at[segment].set(ids, mode="drop")
    valid = episodes > 0
    return LevelResults(
        level_id=jnp.where(valid[:, None], row_id, 0).astype(jnp.uint32),
        valid=valid,
        episodes=episodes,
        solved=total((solved & done).astype(jnp.int32)),
        return_sum=total(episode_return.astype(jnp.float32)),
        return_max=jnp.where(valid, return_max, 0.0),
        value_sum=total(value_mean),
        pvl_sum=total(pvl),
        l1_sum=total(l1),
        policy_version=jnp.full(rows, policy_version, jnp.int32),
    )


def results_to_host(results: LevelResults) -> dict[str, np.ndarray]:
    """The valid rows as numpy arrays (for the wire and for people)."""
    host = jax.device_get(results)
    keep = np.asarray(host.valid, bool)
    return {name: np.asarray(getattr(host, name))[keep] for name in RESULT_FIELDS if name != "valid"}


@functools.cache
def _padding(rows: int) -> LevelResults:
    """The shapes and dtypes of `empty_results(rows)`, worked out once per size (no device work per chunk)."""
    return jax.eval_shape(lambda: empty_results(rows))


def results_from_host(arrays: dict[str, np.ndarray], rows: int) -> LevelResults:
    """Host arrays of n <= rows results (as `results_to_host` gives) padded to `rows` rows."""
    count = int(np.asarray(arrays["episodes"]).shape[0])
    if count > rows:
        raise ValueError(f"{count} level results do not fit in {rows} rows")
    padded = {}
    for name, empty in zip(RESULT_FIELDS, _padding(rows), strict=True):
        if name == "valid":
            padded[name] = np.arange(rows) < count
            continue
        out = np.zeros(empty.shape, empty.dtype)
        out[:count] = np.asarray(arrays[name]).astype(empty.dtype)
        padded[name] = out
    return LevelResults(**padded)
