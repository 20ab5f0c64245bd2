"""New levels made ahead of requests: the maker keeps filtered batches ready on its own thread, draws a batch
unfiltered (and counts it) when requests outrun it, serves a handed-back batch next and reports a failure; a
curriculum's `sample` uses the levels it is given exactly where the batch needs new ones."""

from __future__ import annotations

import functools
import threading
import time

import jax
import numpy as np
import pytest

from impulse.curriculum.ahead import LevelMaker
from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods import Curriculum, make_curriculum
from impulse.curriculum.state import ORIGIN_NEW, ORIGIN_REPLAY
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import level_id_values
from tests.support.quick_compile import quick_jit

BATCH = 4
SPEC = EnvSpec()


def ids(levels) -> list[int]:
    return level_id_values(np.asarray(levels.level_id)).tolist()


@functools.cache
def curriculum(method: str) -> Curriculum:
    config = CurriculumConfig(method=method, buffer_size=2, min_fill=0.5, replay_prob=1.0, noop_filter=False)
    return make_curriculum(config, SPEC, EnvParams(), BATCH)


@functools.cache
def random_levels():
    return quick_jit(lambda key: curriculum("dr").random_levels(key, BATCH))


def test_the_maker_keeps_batches_ready_and_draws_unfiltered_when_none_is():
    gate = threading.Event()
    gate.set()
    made_by_filter: list[list[int]] = []

    def filtered(key):  # a filter that takes as long as the test wants
        gate.wait()
        batch = random_levels()(key)
        made_by_filter.append(ids(batch))
        return batch

    maker = LevelMaker(filtered, random_levels(), jax.random.PRNGKey(0), depth=2)
    maker.start()
    try:
        deadline = time.monotonic() + 60
        while maker.made < 2 or maker.ready < 2:
            assert time.monotonic() < deadline, "the maker never filled its two places"
            time.sleep(0.01)
        gate.clear()  # from now on the filter is slower than the requests
        first, filtered_first = maker.take()
        second, _ = maker.take()
        assert filtered_first and ids(first) == made_by_filter[0] and ids(second) == made_by_filter[1]
        deadline = time.monotonic() + 60
        while maker.ready or not maker.can_draw_unfiltered:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        started = time.perf_counter()
        drawn, was_filtered = maker.take()
        assert not was_filtered and maker.unfiltered == 1 and time.perf_counter() - started < 5
        assert not set(ids(drawn)) & {i for batch in made_by_filter for i in batch}
        maker.give_back(second, True)
        again, was_filtered = maker.take()
        assert was_filtered and ids(again) == ids(second)
        unused, was_filtered = maker.take()  # drawn unfiltered, then not used: dropped and not counted
        assert not was_filtered and maker.unfiltered == 2
        maker.give_back(unused, False)
        assert maker.unfiltered == 1 and maker.ready == 0
    finally:
        gate.set()
        maker.close()
    assert not maker.running


def test_a_failing_filter_is_reported_not_hidden():
    def broken(key):
        raise ValueError("the filter broke")

    maker = LevelMaker(broken, random_levels(), jax.random.PRNGKey(0), depth=1)
    with pytest.raises(RuntimeError, match="making filtered levels failed") as raised:
        maker.start(timeout_s=30)
    assert isinstance(raised.value.__cause__, ValueError)
    maker.close()


@pytest.mark.parametrize("method", ["dr", "plr", "sfl"])
def test_sample_uses_the_new_levels_it_is_given(method):
    cur = curriculum(method)
    fresh = random_levels()(jax.random.PRNGKey(7))
    sample = quick_jit(cur.sample)
    state = cur.init(jax.random.PRNGKey(1))
    state, batch = sample(state, jax.random.PRNGKey(2), fresh)
    assert int(state.counters.new_batches) == 1
    assert ids(batch.levels) == ids(fresh) and (np.asarray(batch.origin) == ORIGIN_NEW).all()
    if method != "plr":
        return
    # A full buffer and replay_prob 1: the next batch is replayed and leaves the new levels unused.
    for i in range(2):
        state, _ = cur.insert(state, jax.tree.map(lambda x, i=i: x[i], fresh))
    state, batch = sample(state, jax.random.PRNGKey(3), random_levels()(jax.random.PRNGKey(8)))
    assert int(state.counters.new_batches) == 1 and (np.asarray(batch.origin) == ORIGIN_REPLAY).all()
    assert set(ids(batch.levels)) <= set(ids(fresh)[:2])
