"""Scores, prioritisation, staleness, insertion and eviction against small hand-computed examples."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods import make_curriculum
from impulse.curriculum.priority import eviction_slot, pick_replays, replay_distribution, score_of
from impulse.curriculum.results import results_from_host
from impulse.curriculum.state import empty_state
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import level_from_scene, level_id_words
from impulse.engine.physics.building import empty_scene
from impulse.engine.physics.sizes import SIZE_S

SPEC = EnvSpec()
EXAMPLE = level_from_scene(empty_scene(SIZE_S))
BATCH = 2


def make_state(config: CurriculumConfig, scores=(), last_sampled=(), clock=0):
    """A buffer whose first len(scores) slots are filled with ids 1, 2, ... and the given scores."""
    state = empty_state(config, EXAMPLE, BATCH, knobs_of(config))
    n = len(scores)
    buffer = state.buffer
    ids = np.stack([level_id_words(i + 1) for i in range(n)]) if n else np.zeros((0, 2), np.uint32)
    buffer = buffer._replace(
        filled=buffer.filled.at[:n].set(True),
        score=buffer.score.at[:n].set(jnp.asarray(scores, jnp.float32)),
        last_sampled=buffer.last_sampled.at[:n].set(jnp.asarray(last_sampled or [0] * n, jnp.int32)),
        levels=buffer.levels.replace(level_id=buffer.levels.level_id.at[:n].set(ids)),
    )
    return state._replace(buffer=buffer, counters=state.counters._replace(clock=jnp.asarray(clock, jnp.int32)))


def knobs_of(config: CurriculumConfig):
    """The live knobs a curriculum of `config` starts with."""
    return make_curriculum(config, SPEC, EnvParams(), BATCH).knobs(config)


def knobs(**changes):
    return knobs_of(CurriculumConfig(**changes))


def test_rank_prioritisation_matches_hand_computation():
    state = make_state(CurriculumConfig(buffer_size=4), scores=[3.0, 1.0, 2.0])
    p = replay_distribution(state.buffer, knobs(staleness_coef=0.0, temperature=1.0), state.counters.clock)
    np.testing.assert_allclose(p, np.array([6, 2, 3, 0]) / 11, rtol=1e-6)  # h = 1, 1/3, 1/2
    p = replay_distribution(state.buffer, knobs(staleness_coef=0.0, temperature=0.5), state.counters.clock)
    np.testing.assert_allclose(p, np.array([36, 4, 9, 0]) / 49, rtol=1e-6)  # h^2


def test_power_prioritisation_clips_negative_scores():
    state = make_state(CurriculumConfig(buffer_size=4), scores=[3.0, -1.0, 1.0])
    p = replay_distribution(state.buffer, knobs(staleness_coef=0.0, prioritization="power"), state.counters.clock)
    np.testing.assert_allclose(p, [0.75, 0.0, 0.25, 0.0], rtol=1e-6)


def test_staleness_mixes_in_and_falls_back_to_uniform():
    state = make_state(CurriculumConfig(buffer_size=4), scores=[3.0, 1.0, 2.0], last_sampled=[0, 5, 8], clock=10)
    p = replay_distribution(state.buffer, knobs(staleness_coef=0.3), state.counters.clock)
    by_rank, by_age = np.array([6, 2, 3, 0]) / 11, np.array([10, 5, 2, 0]) / 17
    np.testing.assert_allclose(p, 0.7 * by_rank + 0.3 * by_age, rtol=1e-6)
    fresh = make_state(CurriculumConfig(buffer_size=4), scores=[3.0, 1.0, 2.0], last_sampled=[7, 7, 7], clock=7)
    p = replay_distribution(fresh.buffer, knobs(staleness_coef=1.0), fresh.counters.clock)
    np.testing.assert_allclose(p, [1 / 3, 1 / 3, 1 / 3, 0], rtol=1e-6)


def test_sequential_picks_reset_staleness_before_the_next_pick():
    state = make_state(CurriculumConfig(buffer_size=2), scores=[1.0, 1.0], last_sampled=[0, 0], clock=1)
    buffer, clock, slots = pick_replays(state.buffer, knobs(staleness_coef=1.0), state.counters.clock,
                                        jax.random.PRNGKey(3), 6)
    slots = np.asarray(slots)
    assert all(slots[i] != slots[i + 1] for i in range(5)), slots  # the picked level's staleness is now 0
    assert int(clock) == 7 and np.asarray(buffer.replays).sum() == 6
    assert int(buffer.last_sampled[slots[-1]]) == 7


def test_eviction_targets_free_slot_then_lowest_replay_probability_or_score():
    config = CurriculumConfig(buffer_size=3)
    partly = make_state(config, scores=[1.0, 2.0])
    assert int(eviction_slot(partly.buffer, partly.knobs, partly.counters.clock, False)) == 2
    # Slot 0 has the top score but is very stale; with rho = 0.9 slot 1 (lowest score, fresh) has the lowest P.
    full = make_state(config, scores=[3.0, 1.0, 2.0], last_sampled=[0, 99, 50], clock=100)
    k = knobs(staleness_coef=0.9)
    assert int(eviction_slot(full.buffer, k, full.counters.clock, False)) == 1
    stale_low = make_state(config, scores=[1.0, 3.0, 2.0], last_sampled=[0, 99, 99], clock=100)
    assert int(eviction_slot(stale_low.buffer, k, stale_low.counters.clock, False)) != 0  # staleness protects it
    assert int(eviction_slot(stale_low.buffer, k, stale_low.counters.clock, True)) == 0  # SFL: lowest score


def test_score_functions():
    f = lambda name, **kw: float(score_of(jnp.asarray(  # noqa: E731
        ["maxmc", "pvl", "l1_value_loss", "learnability"].index(name)), **kw))
    inputs = dict(episodes=jnp.float32(4), solved=jnp.float32(1), max_return=jnp.float32(1.5),
                  value_sum=jnp.float32(2.0), pvl_sum=jnp.float32(0.8), l1_sum=jnp.float32(1.2),
                  window_episodes=jnp.int32(2))
    assert f("maxmc", **inputs) == pytest.approx(1.5 - 1.0)
    assert f("pvl", **inputs) == pytest.approx(0.4)
    assert f("l1_value_loss", **inputs) == pytest.approx(0.6)
    assert f("learnability", **inputs) == pytest.approx(0.25 * 0.75 + 0.001 * 0.25)


def _results(rows, ids, episodes, solved, value_sum=None, return_max=None, version=0):
    n = len(ids)
    arrays = dict(
        level_id=np.stack([level_id_words(i) for i in ids]),
        episodes=np.asarray(episodes), solved=np.asarray(solved), return_sum=np.zeros(n),
        return_max=np.asarray(return_max if return_max is not None else np.zeros(n)),
        value_sum=np.asarray(value_sum if value_sum is not None else np.zeros(n)),
        pvl_sum=np.zeros(n), l1_sum=np.zeros(n), policy_version=np.full(n, version))
    return results_from_host(arrays, rows)


def _stage(state, ids):
    staging = state.staging
    n = len(ids)
    words = np.stack([level_id_words(i) for i in ids])
    return state._replace(staging=staging._replace(
        staged=staging.staged.at[:n].set(True),
        levels=staging.levels.replace(level_id=staging.levels.level_id.at[:n].set(words))))


@pytest.fixture(scope="module")
def learnability_plr():
    config = CurriculumConfig(method="plr", buffer_size=2, score="learnability", staleness_coef=0.0,
                              candidate_episodes=2, score_memory=1.0)
    return config, jax.jit(make_curriculum(config, SPEC, EnvParams(), BATCH).update)


def test_insertion_waits_for_episodes_fills_free_slots_then_replaces_only_a_strictly_better(learnability_plr):
    config, update = learnability_plr
    state = _stage(make_state(config), [11, 12, 13, 14])
    # 11 has one episode of the two it needs: stays staged. 12 and 13 fill the free slots whatever their score.
    state = update(state, _results(8, [11, 12, 13], [1, 2, 4], [1, 0, 2]))
    ids = lambda s: sorted(int(x) for x, f in zip(np.asarray(s.buffer.levels.level_id)[:, 1],  # noqa: E731
                                                  np.asarray(s.buffer.filled)) if f)
    assert ids(state) == [12, 13] and bool(state.staging.staged[0])
    assert float(state.buffer.score[0]) == pytest.approx(0.0)  # 12: never solved
    # 14 ties 12 (never solved): strictly better is required, so it is rejected.
    state = update(state, _results(8, [14], [2], [0]))
    assert ids(state) == [12, 13] and int(state.counters.rejected) == 1
    # 11's second episode makes p = 1/2: it replaces the lowest-probability slot (12, score 0), an eviction.
    state = update(state, _results(8, [11], [1], [0]))
    assert ids(state) == [11, 13] and int(state.counters.evicted) == 1 and int(state.counters.inserted) == 3
    assert not bool(state.staging.staged[:4].any())


def test_levels_move_with_their_ids_when_one_update_fills_a_slot_twice(learnability_plr):
    """One update in which 11 and 12 fill the two free slots, 13 then replaces the lowest (12) and a last row
    re-scores 13 where it now is: each buffered level is the whole staged level of its id (the levels are copied
    once, after the rows, from the last candidate accepted into each slot)."""
    config, update = learnability_plr
    state = _stage(make_state(config), [11, 12, 13])
    marks = jnp.arange(state.staging.levels.densities.shape[0], dtype=jnp.float32)[:, None] + 100.0
    staging = state.staging
    state = state._replace(staging=staging._replace(levels=staging.levels.replace(
        densities=jnp.broadcast_to(marks, staging.levels.densities.shape))))
    state = update(state, _results(8, [11, 12, 13, 13], [2, 2, 2, 2], [1, 0, 1, 1]))
    words = np.asarray(state.buffer.levels.level_id)[:, 1]
    assert sorted(words.tolist()) == [11, 13] and int(state.counters.evicted) == 1
    for slot, level_id in enumerate(words):
        staged_slot = [11, 12, 13].index(int(level_id))
        assert np.all(np.asarray(state.buffer.levels.densities[slot]) == 100.0 + staged_slot), (slot, level_id)
    thirteen = int(np.flatnonzero(words == 13)[0])
    assert float(state.buffer.episodes[thirteen]) == pytest.approx(4.0), "the last row re-scored 13 in its slot"


def test_results_for_buffered_levels_rescore_in_place_and_unknown_ids_are_counted(learnability_plr):
    config, update = learnability_plr
    state = make_state(config, scores=[0.0, 0.0])
    state = update(state, _results(8, [1, 2, 99], [4, 4, 1], [2, 4, 1], version=7))
    np.testing.assert_allclose(state.buffer.score, [0.25 + 0.0005, 0.001], rtol=1e-5)
    assert list(np.asarray(state.buffer.score_version)) == [7, 7]
    assert int(state.counters.unknown_results) == 1
    words = np.asarray(state.buffer.levels.level_id)[np.asarray(state.buffer.filled)]
    assert len({tuple(w) for w in words}) == int(np.asarray(state.buffer.filled).sum())  # no duplicate ids


def test_knob_values_are_checked():
    with pytest.raises(ValueError, match="replay_prob must be in"):
        CurriculumConfig(replay_prob=1.5)
    with pytest.raises(ValueError, match="num_edits must be in"):
        dataclasses.replace(CurriculumConfig(), num_edits=99)
