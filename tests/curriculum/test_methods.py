"""The registry of curriculum methods: the names the config accepts are the methods there are, each builds the
class that implements it, and what a method declares (its candidate episodes, batch scoring) reaches its callers."""

from __future__ import annotations

import typing

import pytest

from impulse.curriculum import config as config_module
from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods import METHODS, make_curriculum
from impulse.engine.env.spec import EnvParams, EnvSpec


def test_the_config_names_exactly_the_registered_methods():
    assert tuple(METHODS) == config_module.METHODS
    assert typing.get_args(config_module.Method) == config_module.METHODS


@pytest.mark.parametrize("method", list(METHODS))
def test_make_curriculum_builds_the_method_the_config_names(method):
    curriculum = make_curriculum(CurriculumConfig(method=method), EnvSpec(), EnvParams(), 4)
    assert type(curriculum) is METHODS[method] and curriculum.method == method


@pytest.mark.parametrize(("method", "episodes"), [("dr", 1), ("plr", 1), ("accel", 1), ("sfl", 4)])
def test_candidate_episodes_default_to_the_methods_own_count_unless_set(method, episodes):
    curriculum = make_curriculum(CurriculumConfig(method=method), EnvSpec(), EnvParams(), 4)
    assert int(curriculum.knobs(curriculum.config).candidate_episodes) == episodes
    assert int(curriculum.knobs(CurriculumConfig(method=method, candidate_episodes=7)).candidate_episodes) == 7


def test_only_batch_scored_sfl_refills():
    scored = {(method, scoring): make_curriculum(CurriculumConfig(method=method, sfl_scoring=scoring), EnvSpec(),
                                                 EnvParams(), 4).batch_scored
              for method in METHODS for scoring in ("online", "batch")}
    assert [key for key, value in scored.items() if value] == [("sfl", "batch")]
    plr = make_curriculum(CurriculumConfig(method="plr"), EnvSpec(), EnvParams(), 4)
    with pytest.raises(NotImplementedError, match="plr"):
        plr.refill(None, None, None, 0)
