"""The curricula on levels whose true solve rate is known: a synthetic player reports binomial outcomes, so what
each buffer keeps can be checked against the truth. Real random levels (no no-op filter, to keep it cheap).

Compiling `sample` is most of the cost (about 20 CPU seconds per method, 65 for ACCEL's mutation, at XLA's usual
optimisation; `quick_jit` takes about 40% off), so the tests share programs: one per static configuration (method,
scoring form, buffer and batch sizes), each test setting its live knobs in the state, which is what a live change
does; PLR's replay test runs on ACCEL's program."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods import make_curriculum
from impulse.curriculum.priority import score_weights
from impulse.curriculum.results import results_from_host
from impulse.curriculum.state import ORIGIN_MUTATED, ORIGIN_NEW, ORIGIN_REPLAY
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import level_id_values, level_id_words
from impulse.engine.physics.validate import validate_scene
from tests.support.quick_compile import quick_jit

SPEC = EnvSpec()
BATCH = 16
BUFFER = 32
MAX_EDITS = 2  # ACCEL's static bound on the live num_edits, and num_edits itself
TRUE_RATES = np.array([0.0, 0.25, 0.5, 0.75, 1.0])  # by id modulo 5: 40% of levels are not learnable


def true_rate(ids: np.ndarray) -> np.ndarray:
    return TRUE_RATES[(ids % np.uint64(len(TRUE_RATES))).astype(int)]


def config(**settings) -> CurriculumConfig:
    return CurriculumConfig(buffer_size=BUFFER, noop_filter=False, max_edits=MAX_EDITS, **{"num_edits": MAX_EDITS,
                                                                                          **settings})


def compiled(method: str, sfl_scoring: str = "online"):
    """The curriculum of one static configuration with its jitted sample and update; the live knobs a test sets
    come with the state (`start`)."""
    return _compiled(method, sfl_scoring)


@functools.cache
def _compiled(method: str, sfl_scoring: str):
    curriculum = make_curriculum(config(method=method, sfl_scoring=sfl_scoring), SPEC, EnvParams(), BATCH)
    return curriculum, quick_jit(curriculum.sample), quick_jit(curriculum.update)


@functools.cache
def _init():
    """`init`, the same for every method (an empty buffer and staging area of these sizes), compiled once."""
    return quick_jit(compiled("sfl")[0].init)


def start(seed: int, **settings):
    """The empty state `init` gives a curriculum configured by `settings` (its live knobs)."""
    configured = config(**settings)
    knobs = make_curriculum(configured, SPEC, EnvParams(), BATCH).knobs(configured)
    return _init()(jax.random.PRNGKey(seed))._replace(knobs=knobs)


def play(batch, rng: np.random.Generator, episodes: int, version: int):
    """Results as the synthetic player reports them: `episodes` per distinct level, solved ~ Binomial."""
    ids = np.unique(level_id_values(np.asarray(batch.levels.level_id)))
    n = ids.size
    solved = rng.binomial(episodes, true_rate(ids))
    arrays = dict(level_id=np.stack([level_id_words(int(i)) for i in ids]), episodes=np.full(n, episodes),
                  solved=solved, return_sum=solved.astype(float), return_max=(solved > 0).astype(float),
                  value_sum=episodes * true_rate(ids), pvl_sum=np.zeros(n), l1_sum=np.zeros(n),
                  policy_version=np.full(n, version))
    return results_from_host(arrays, 2 * BATCH)


def run(settings: dict, rounds: int, seed: int = 0, episodes: int = 2, program: str | None = None):
    """`rounds` of sample and update from an empty state; `program`: the method whose compiled functions run them
    (default: the one `settings` names)."""
    _, sample, update = compiled(program or settings["method"], settings.get("sfl_scoring", "online"))
    rng = np.random.default_rng(seed)
    state = start(seed, **settings)
    batches = []
    for i in range(rounds):
        state, batch = sample(state, jax.random.PRNGKey(1000 * seed + i))
        batches.append(batch)
        state = update(state, play(batch, rng, episodes, i))
    return state, batches


def buffered_ids(state) -> np.ndarray:
    filled = np.asarray(state.buffer.filled)
    return level_id_values(np.asarray(state.buffer.levels.level_id)[filled])


def test_sfl_buffer_holds_mostly_learnable_levels():
    state, batches = run(dict(method="sfl", candidate_episodes=4, sfl_ratio=0.5), rounds=40)
    ids = buffered_ids(state)
    rates = true_rate(ids)
    learnable = ((rates > 0) & (rates < 1)).mean()
    assert ids.size == BUFFER and np.unique(ids).size == ids.size
    assert learnable >= 0.8, f"only {learnable:.0%} of SFL's buffer is learnable (generator: 60%)"
    late = batches[-1]
    from_buffer = np.asarray(late.origin) == ORIGIN_REPLAY
    assert from_buffer.sum() == BATCH // 2 and np.asarray(late.train).all()


def test_plr_replays_by_rank():
    """Once full, replay picks follow 1/rank: the empirical pick frequency of each level matches P_S. Run on
    ACCEL's compiled functions (ACCEL's replay batches are PLR's; its children only add candidates): the last of
    the 31 rounds is a batch of children, so the next sample is a replay."""
    settings = dict(method="plr", score="learnability", staleness_coef=0.0, replay_prob=1.0, min_fill=0.0,
                    temperature=0.5)
    state, batches = run(settings, rounds=31, seed=1, episodes=4, program="accel")
    _, sample, _ = compiled("accel")
    assert (np.asarray(batches[-1].origin) == ORIGIN_MUTATED).all() and not bool(state.mutate_next)
    expected = np.asarray(score_weights(state.buffer, state.knobs))
    counts = np.zeros_like(expected)
    slots = {int(v): s for s, v in enumerate(level_id_values(np.asarray(state.buffer.levels.level_id)))}
    for i in range(40):  # without updates the scores stay put
        _, batch = sample(state, jax.random.PRNGKey(5000 + i))
        assert (np.asarray(batch.origin) == ORIGIN_REPLAY).all()
        for value in level_id_values(np.asarray(batch.levels.level_id)):
            counts[slots[int(value)]] += 1
    frequency = counts / counts.sum()
    top = np.argsort(-expected)[:3]
    np.testing.assert_allclose(frequency[top], expected[top], atol=0.05)
    assert frequency[np.argmax(expected)] > 2 * frequency[np.argsort(-expected)[8]]


def test_accel_children_are_valid_levels_with_their_parents_recorded():
    _, sample, update = compiled("accel")
    rng = np.random.default_rng(2)
    state = start(2, method="accel", replay_prob=1.0, min_fill=0.25)
    for i in range(8):
        state, batch = sample(state, jax.random.PRNGKey(i))
        if np.asarray(batch.origin)[0] == ORIGIN_REPLAY:
            parents = level_id_values(np.asarray(batch.levels.level_id))
            state, children = sample(state, jax.random.PRNGKey(100 + i))
            break
        state = update(state, play(batch, rng, 2, i))
    else:
        pytest.fail("ACCEL never replayed")
    assert (np.asarray(children.origin) == ORIGIN_MUTATED).all()
    child_ids = level_id_values(np.asarray(children.levels.level_id))
    assert not set(child_ids) & set(parents)
    staged = np.asarray(state.staging.staged)
    staged_ids = level_id_values(np.asarray(state.staging.levels.level_id))
    lineage = dict(zip(staged_ids[staged], level_id_values(np.asarray(state.staging.parent_id))[staged],
                       strict=True))
    assert [lineage[c] for c in child_ids] == list(parents)
    on_host = jax.tree.map(np.asarray, children.levels)
    for i in range(BATCH):
        assert not validate_scene(jax.tree.map(lambda x, i=i: x[i], on_host).state), i


def test_batch_scored_sfl_keeps_the_most_learnable_candidates_and_replays_at_once():
    curriculum, sample, update = compiled("sfl", "batch")
    state = start(0, method="sfl", sfl_scoring="batch", sfl_ratio=0.5)
    # 64 candidates: the fresh levels of four batches sampled while the buffer is empty (no program of their own)
    fresh = [sample(state, jax.random.PRNGKey(1000 + i))[1] for i in range(4)]
    assert all((np.asarray(batch.origin) == ORIGIN_NEW).all() for batch in fresh)
    candidates = jax.tree.map(lambda *xs: jax.numpy.concatenate(xs), *(batch.levels for batch in fresh))
    ids = level_id_values(np.asarray(candidates.level_id))
    rates = true_rate(ids)  # learnability 0, 0.19, 0.25, 0.19 and 0.001 (always solved) by id modulo 5
    state = quick_jit(curriculum.refill)(state, candidates, jax.numpy.asarray(rates, jax.numpy.float32), 7)
    kept = buffered_ids(state)
    learnable = ids[(rates > 0) & (rates < 1)]
    assert not set(kept) & set(ids[rates == 0]), "a never-solved level entered the buffer"
    assert kept.size == min(BUFFER, (rates > 0).sum())
    if learnable.size >= BUFFER:  # the learnable levels come before the always-solved ones
        assert set(kept) <= set(learnable)
    else:
        assert set(kept) >= set(learnable)
    # the most learnable first: every level at p = 0.5 is kept before any at p = 0.25 or 0.75
    half = ids[rates == 0.5]
    assert set(half[:BUFFER]) <= set(kept)
    assert (np.asarray(state.buffer.score_version)[np.asarray(state.buffer.filled)] == 7).all()

    state, batch = sample(state, jax.random.PRNGKey(2))
    from_buffer = np.asarray(batch.origin) == ORIGIN_REPLAY
    assert from_buffer.sum() == BATCH // 2, "batch-scored SFL replays from its first batch"
    assert set(level_id_values(np.asarray(batch.levels.level_id))[from_buffer]) <= set(kept)
    # training results do not touch the buffer: only the next refill does
    after = update(state, play(batch, np.random.default_rng(0), 4, 8))
    np.testing.assert_array_equal(np.asarray(after.buffer.score), np.asarray(state.buffer.score))
    assert int(after.counters.results) > int(state.counters.results)
