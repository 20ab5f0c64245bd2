"""Key expressions: their shapes, and names that would break them."""

from __future__ import annotations

import pytest

from bus.keys import SCHEMA_MAJOR, Keys, check_name


def test_keys_sit_under_run_and_major_version() -> None:
    keys = Keys("run-7")
    root = f"impulse/run-7/v{SCHEMA_MAJOR}"
    assert SCHEMA_MAJOR == 1
    assert keys.root == root
    assert keys.traj("a3") == f"{root}/traj/a3"
    assert keys.traj_all == f"{root}/traj/*"
    assert keys.credit("a3") == f"{root}/credit/a3"
    assert keys.weights_policy == f"{root}/weights/policy"
    assert keys.weights_latest == f"{root}/weights/latest"
    assert keys.levels_sample == f"{root}/levels/sample"
    assert keys.levels_results("a3") == f"{root}/levels/results/a3"
    assert keys.curriculum_knobs == f"{root}/curriculum/knobs"
    assert keys.curriculum_inspect == f"{root}/curriculum/inspect"
    assert keys.levels_results_all == f"{root}/levels/results/*"
    assert keys.ctrl("actor", "a3") == f"{root}/ctrl/actor/a3"
    assert keys.ctrl_all == f"{root}/ctrl/all"
    assert keys.metrics("learner", "0") == f"{root}/metrics/learner/0"
    assert keys.metrics_all == f"{root}/metrics/**"
    assert keys.alive("actor", "a3") == f"{root}/alive/actor/a3"
    assert keys.alive_pattern("actor") == f"{root}/alive/actor/*"
    assert keys.alive_pattern() == f"{root}/alive/**"


def test_parse_alive_round_trips_and_refuses_other_keys() -> None:
    keys = Keys("r")
    assert keys.parse_alive(keys.alive("curriculum", "main")) == ("curriculum", "main")
    for bad in [Keys("other").alive("actor", "a0"), keys.traj("a0"), f"{keys.root}/alive/x", f"{keys.root}/alive/a/b/"]:
        with pytest.raises(ValueError, match="not a liveliness key"):
            keys.parse_alive(bad)


@pytest.mark.parametrize("name", ["", "a/b", "a*", "$x", "a#b", "what?", "a b", "tab\there", "line\n"])
def test_bad_names_are_refused(name: str) -> None:
    with pytest.raises(ValueError, match="actor id"):
        check_name(name, "actor id")
    with pytest.raises(ValueError, match="actor id"):
        Keys("r").traj(name)
    with pytest.raises(ValueError, match="run id"):
        Keys(name)


def test_good_names_pass_unchanged() -> None:
    for name in ["a0", "actor-12", "run_2024.06.01", "UPPER"]:
        assert check_name(name, "id") == name
