"""benchmarks/open_loop.py on one of our easy hand-made levels, at small sizes: the plan families are built as
described, an episode counts as solved only when the level's goal is reached, and the shipped agent's part says how
it plays the level and how much it leans on the actions that solve it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from impulse.benchmarks.open_loop import constant_plans, main, window_plans
from tests.support.paths import REPO


def test_the_plan_families_cover_the_action_space() -> None:
    nvec = (3, 2)
    constant = constant_plans(nvec, steps=5)
    assert constant.actions.shape == (6, 5, 2) and constant.labels[0] == "hold [0, 0]"
    window = window_plans(nvec, steps=6, starts=[1], lengths=[2])
    assert window.actions.shape == (3, 6, 2)  # dimension 0 = 1, dimension 0 = 2, dimension 1 = 1
    np.testing.assert_array_equal(window.actions[1][:, 0], [0, 2, 2, 0, 0, 0])
    assert window.labels[2] == "dimension 1 = 1 during steps [1, 3)"


def test_firing_the_thruster_solves_easy_thrust_right_and_resting_does_not(capsys: pytest.CaptureFixture[str]) -> None:
    [agent] = (REPO / "pretrained" / "general-s" / "checkpoints").iterdir()  # one checkpoint's folder, by step
    assert main(["--levels", "handmade:s_easy_thrust_right", "--random", "4", "--window-starts", "0",
                 "--window-lengths", "256", "--batch", "64", "--agent", str(agent), "--agent-episodes", "8"]) == 0
    config, level = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert config["record"] == "config" and level["level"] == "s_easy_thrust_right"
    assert config["agent"] == str(agent) and config["agent_episodes"] == 8
    assert level["constant"]["episodes"] == 324 and level["window"]["episodes"] == 10
    assert 0 < level["constant"]["solved"] < 324
    assert "hold [0, 0, 0, 0, 0, 0]" not in level["constant"]["first"]  # at rest nothing moves: no solve
    assert "dimension 4 = 1 during steps [0, 256)" in level["window"]["first"]
    played = level["agent"]
    assert played["episodes"] == 8 and played["solve_rate"] >= 0.75  # it solves this level zero-shot (README)
    assert played["solving_hold_share"] == level["constant"]["solved"] / 324
    # It solves the level by leaning on the solving actions: more probability on them than a uniform policy gives.
    assert played["solving_hold_mass_early"] > played["solving_hold_share"]
    assert 0 < played["solving_hold_mass_first_step"] <= 1 and 0 < played["solving_hold_mass_episode"] <= 1
