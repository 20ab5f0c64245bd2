"""The curricula on levels whose true solve rate is known: a synthetic player reports binomial outcomes, so what
each buffer keeps can be checked against the truth. Real random levels (no no-op filter, to keep it cheap)."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest
from impulse.curriculum.algorithms import Curriculum
from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.priority import score_weights
from impulse.curriculum.results import results_from_host
from impulse.curriculum.state import ORIGIN_MUTATED, ORIGIN_REPLAY
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import level_id_values, level_id_words
from impulse.engine.physics.validate import validate_scene

SPEC = EnvSpec()
BATCH = 16
TRUE_RATES = np.array([0.0, 0.25, 0.5, 0.75, 1.0])  # by id modulo 5: 40% of levels are not learnable


def true_rate(ids: np.ndarray) -> np.ndarray:
    return TRUE_RATES[(ids % np.uint64(len(TRUE_RATES))).astype(int)]


@functools.cache
def compiled(**settings):
    config = CurriculumConfig(buffer_size=32, noop_filter=False, **settings)
    curriculum = Curriculum(config, SPEC, EnvParams(), BATCH)
    return curriculum, jax.jit(curriculum.init), jax.jit(curriculum.sample), jax.jit(curriculum.update)


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


def run(settings: dict, rounds: int, seed: int = 0, episodes: int = 2):
    curriculum, init, sample, update = compiled(**settings)
    rng = np.random.default_rng(seed)
    state = init(jax.random.PRNGKey(seed))
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
    assert ids.size == 32 and np.unique(ids).size == ids.size
    assert learnable >= 0.8, f"only {learnable:.0%} of SFL's buffer is learnable (generator: 60%)"
    late = batches[-1]
    from_buffer = np.asarray(late.origin) == ORIGIN_REPLAY
    assert from_buffer.sum() == BATCH // 2 and np.asarray(late.train).all()


def test_plr_replays_by_rank():
    """Once full, replay picks follow 1/rank: the empirical pick frequency of each level matches P_S."""
    settings = dict(method="plr", score="learnability", staleness_coef=0.0, replay_prob=1.0, min_fill=0.0,
                    temperature=0.5)
    state, _ = run(settings, rounds=30, seed=1, episodes=4)
    curriculum, _, sample, _ = compiled(**settings)
    expected = np.asarray(score_weights(state.buffer, state.knobs))
    counts = np.zeros_like(expected)
    for i in range(40):  # without updates the scores stay put
        _, batch = sample(state, jax.random.PRNGKey(5000 + i))
        picked = level_id_values(np.asarray(batch.levels.level_id))
        slots = {int(v): s for s, v in enumerate(level_id_values(np.asarray(state.buffer.levels.level_id)))}
        for value in picked:
            counts[slots[int(value)]] += 1
    frequency = counts / counts.sum()
    top = np.argsort(-expected)[:3]
    np.testing.assert_allclose(frequency[top], expected[top], atol=0.05)
    assert frequency[np.argmax(expected)] > 2 * frequency[np.argsort(-expected)[8]]


def test_accel_children_are_valid_levels_with_their_parents_recorded():
    settings = dict(method="accel", replay_prob=1.0, min_fill=0.25, num_edits=2, max_edits=2)
    curriculum, init, sample, update = compiled(**settings)
    rng = np.random.default_rng(2)
    state = init(jax.random.PRNGKey(2))
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
    for i in range(BATCH):
        child = jax.tree.map(lambda x, i=i: np.asarray(x[i]), children.levels)
        assert not validate_scene(child.state), i


def test_batch_scored_sfl_keeps_the_most_learnable_candidates_and_replays_at_once():
    curriculum, init, sample, update = compiled(method="sfl", sfl_scoring="batch", sfl_ratio=0.5)
    state = init(jax.random.PRNGKey(0))
    candidates = jax.jit(curriculum.new_levels, static_argnums=1)(jax.random.PRNGKey(1), 64)
    ids = level_id_values(np.asarray(candidates.level_id))
    rates = true_rate(ids)  # learnability 0, 0.19, 0.25, 0.19 and 0.001 (always solved) by id modulo 5
    state = jax.jit(curriculum.refill)(state, candidates, jax.numpy.asarray(rates, jax.numpy.float32), 7)
    kept = buffered_ids(state)
    learnable = ids[(rates > 0) & (rates < 1)]
    assert not set(kept) & set(ids[rates == 0]), "a never-solved level entered the buffer"
    assert kept.size == min(32, (rates > 0).sum())
    if learnable.size >= 32:  # the learnable levels come before the always-solved ones
        assert set(kept) <= set(learnable)
    else:
        assert set(kept) >= set(learnable)
    # the most learnable first: every level at p = 0.5 is kept before any at p = 0.25 or 0.75
    half = ids[rates == 0.5]
    assert set(half[:32]) <= set(kept)
    assert (np.asarray(state.buffer.score_version)[np.asarray(state.buffer.filled)] == 7).all()

    state, batch = sample(state, jax.random.PRNGKey(2))
    from_buffer = np.asarray(batch.origin) == ORIGIN_REPLAY
    assert from_buffer.sum() == BATCH // 2, "batch-scored SFL replays from its first batch"
    assert set(level_id_values(np.asarray(batch.levels.level_id))[from_buffer]) <= set(kept)
    # training results do not touch the buffer: only the next refill does
    after = update(state, play(batch, np.random.default_rng(0), 4, 8))
    np.testing.assert_array_equal(np.asarray(after.buffer.score), np.asarray(state.buffer.score))
    assert int(after.counters.results) > int(state.counters.results)
