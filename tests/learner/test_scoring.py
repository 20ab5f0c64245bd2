"""Scoring a policy on level sets (`learner.scoring.score_policy`) in chunks of levels, as the evaluator process does
so that its status can say how many levels are scored: every chunk runs one program of the same size, the levels
are reported in order as each chunk ends, and asking for a chunk at least as large as the set is the one-program
evaluation `impulse eval` and the trainers run, draw for draw."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from impulse.engine.env.config import EnvConfig
from impulse.learner import scoring
from impulse.learner.agent import env_and_agent
from impulse.learner.config import NetworkConfig
from impulse.learner.scoring import LevelSets, evaluating_phase, load_level_sets, score_policy

ATTEMPTS = 2


@pytest.fixture(scope="module")
def policy():
    """A small untrained flat network on symbolic observations, the bundled hand-made S levels, short episodes."""
    spec, env_params, agent = env_and_agent(EnvConfig(observation="symbolic", max_timesteps=32),
                                            NetworkConfig(kind="flat", width=16, depth=1))
    sets = load_level_sets("handmade", spec.sizes)
    return agent, agent.init(jax.random.PRNGKey(0)), env_params, sets


def test_chunks_are_played_by_one_program_and_reported_in_order(policy, monkeypatch: pytest.MonkeyPatch) -> None:
    agent, params, env_params, sets = policy
    total = len(sets.names)
    assert total >= 3, sets.names
    played: list[int] = []
    evaluate = scoring.evaluate

    def counted(agent, params, env_params, levels, key, **kwargs):
        played.append(int(levels.roles.shape[0]))
        return evaluate(agent, params, env_params, levels, key, **kwargs)

    monkeypatch.setattr(scoring, "evaluate", counted)
    heard: list[tuple[int, int, str]] = []
    scored = score_policy(agent, params, env_params, sets, jax.random.PRNGKey(1), ATTEMPTS,
                          on_level=lambda done, of, name, rate: heard.append((done, of, name)), chunk_levels=2)
    assert played == [2] * -(-total // 2), "every chunk the same size, the last one filled up"
    assert heard == [(i + 1, total, name) for i, name in enumerate(sets.names)]
    assert list(scored.table) == sets.names
    assert all(0.0 <= row["solve_rate"] <= 1.0 for row in scored.table.values())


def test_a_chunk_as_large_as_the_set_is_the_one_program_evaluation(policy) -> None:
    agent, params, env_params, all_sets = policy
    # Two levels: the size of the chunks above, so that this test runs the program they compiled.
    names = all_sets.names[:2]
    sets = LevelSets(names, jax.tree.map(lambda x: x[:2], all_sets.levels), {"first two": names})
    key = jax.random.PRNGKey(2)
    whole = score_policy(agent, params, env_params, sets, key, ATTEMPTS)
    chunked = score_policy(agent, params, env_params, sets, key, ATTEMPTS, chunk_levels=len(sets.names) + 5)
    assert chunked.table == whole.table
    assert np.isfinite([row["mean_return"] for row in whole.table.values()]).all()


def test_the_phase_says_how_many_levels_are_scored() -> None:
    assert evaluating_phase(42, 20) == "evaluating 42 levels x 20 attempts"
    assert evaluating_phase(42, 20, 16) == "evaluating 16/42 levels x 20 attempts"
    assert evaluating_phase(1, 1, 0) == "evaluating 0/1 level x 1 attempt"
