"""Key expressions: their shapes, and names that would break them."""

from __future__ import annotations

import pytest

from impulse.bus.keys import SCHEMA_MAJOR, Keys, check_name


def test_each_role_publishes_under_its_own_prefix() -> None:
    keys = Keys("run-7")
    root = f"impulse/run-7/v{SCHEMA_MAJOR}"
    assert SCHEMA_MAJOR == 2
    assert keys.root == root
    learner = [keys.weights_policy, keys.weights_latest, keys.credit("a3"), keys.status("learner", "learner"),
               keys.alive("learner", "learner")]
    curriculum = [keys.levels_sample, keys.curriculum_knobs, keys.curriculum_inspect, keys.status("curriculum", "c")]
    actor = [keys.traj("a3"), keys.levels_results("a3"), keys.status("actor", "a3"), keys.alive("actor", "a3")]
    for role, owned in (("learner", learner), ("curriculum", curriculum), ("actor", actor)):
        assert all(key.startswith(f"{root}/{role}/") for key in owned), (role, owned)
    assert keys.weights_policy == f"{root}/learner/weights/policy"
    assert keys.credit("a3") == f"{root}/learner/credit/a3"
    assert keys.levels_sample == f"{root}/curriculum/levels/sample"
    assert keys.traj("a3") == f"{root}/actor/traj/a3"
    assert keys.traj_all == f"{root}/actor/traj/*"
    assert keys.levels_results_all == f"{root}/actor/results/*"
    assert keys.status("operator", "cli-1") == f"{root}/operator/status/cli-1"
    assert keys.status_pattern() == f"{root}/*/status/*"
    assert keys.status_pattern("learner") == f"{root}/learner/status/*"
    assert keys.alive_pattern("actor") == f"{root}/actor/alive/*"
    assert keys.alive_pattern() == f"{root}/*/alive/*"


def test_role_names_that_are_not_one_key_chunk_are_refused() -> None:
    with pytest.raises(ValueError, match="not allowed in a key chunk"):
        Keys("r").status("launcher/x", "main")
    with pytest.raises(ValueError, match="not allowed in a key chunk"):
        Keys("r").alive_pattern("*")
    with pytest.raises(ValueError, match="role is empty"):
        Keys("r").status("", "main")


def test_parse_alive_and_status_round_trip_and_refuse_other_keys() -> None:
    keys = Keys("r")
    assert keys.parse_alive(keys.alive("curriculum", "main")) == ("curriculum", "main")
    assert keys.parse_status(keys.status("actor", "actor-1")) == ("actor", "actor-1")
    for bad in [Keys("other").alive("actor", "a0"), keys.traj("a0"), f"{keys.root}/actor/alive",
                f"{keys.root}/actor/alive/a/b", f"{keys.root}//alive/a", keys.status("actor", "a0")]:
        with pytest.raises(ValueError, match="not a liveliness key"):
            keys.parse_alive(bad)
    with pytest.raises(ValueError, match="not a status key"):
        keys.parse_status(keys.alive("learner", "learner"))


@pytest.mark.parametrize("name", ["", "a/b", "a*", "$x", "a#b", "what?", "a b", "tab\there", "line\n", "@adv"])
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
