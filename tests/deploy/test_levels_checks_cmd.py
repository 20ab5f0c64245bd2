"""What `impulse levels` and `impulse curriculum inspect` print about a level's use of its slots, a level that
cannot be solved, and whole-count histograms."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from impulse.curriculum.stats import histogram
from impulse.deploy.cli import main
from impulse.deploy.commands.curriculum import format_report, integer_bins
from impulse.engine.levels.kinetix_json import save_kinetix_level
from impulse.engine.physics.sizes import SIZE_S
from tests.support.monitor_scenes import small_level
from tests.support.paths import REPO, SHARED_LEVELS

UNICYCLE = SHARED_LEVELS / "m" / "h0_unicycle.json"


@pytest.mark.skipif(not UNICYCLE.is_file(), reason=f"Kinetix's level files are not at {SHARED_LEVELS}")
def test_show_counts_the_shapes_in_use_not_the_slots(capsys: pytest.CaptureFixture[str]) -> None:
    """m/h0_unicycle has M's slots (3 circles, 2 thrusters) but uses 2 circles and no thruster."""
    assert main(["levels", "show", str(UNICYCLE)]) == 0
    out = capsys.readouterr().out
    assert "size: M; in use: 6 polygons incl. 4 arena, 2 circles, 2 joints, 0 thrusters" in out, out
    assert "thrusters: none" in out and "cannot be solved" not in out


def test_validate_says_when_a_valid_level_cannot_be_solved(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    level = small_level()
    roles = np.array(level.roles)
    roles[4] = 0  # the green box becomes neutral
    no_green = save_kinetix_level(tmp_path / "no_green.json", level.replace(roles=roles), SIZE_S)
    good = save_kinetix_level(tmp_path / "good.json", level, SIZE_S)
    assert main(["levels", "validate", str(tmp_path)]) == 0  # still valid: the exit status is unchanged
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"ok       {good}", f"ok, but cannot be solved: no green shape  {no_green}",
                     "2 of 2 level files valid (1 of them cannot be solved)"]
    assert main(["levels", "show", str(no_green)]) == 0
    assert "(it cannot be solved: no green shape)" in capsys.readouterr().out


def test_the_hand_made_levels_can_all_be_solved(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["levels", "validate", str(REPO / "engine" / "levels" / "handmade"), "--size", "l"]) == 0  # one size
    out = capsys.readouterr().out
    assert "14 of 14 level files valid\n" in out and "cannot be solved" not in out, out


def test_whole_counts_get_integer_bins() -> None:
    zeros = histogram(np.zeros(7))  # numpy's bins around a single value: -0.5 .. 0.5 in tenths
    assert integer_bins(zeros["edges"], zeros["counts"]) == [("0", 7)]
    assert integer_bins(**histogram(np.array([0, 1, 1, 3]))) == [("0", 1), ("1", 2), ("2", 0), ("3", 1)]
    wide = histogram(np.arange(101))
    assert integer_bins(**wide) == [*((f"{k}-{k + 9}", 10) for k in range(0, 90, 10)), ("90-100", 11)]
    assert integer_bins(**histogram(np.array([0.25, 0.5, 3.0]))) is None  # not whole numbers

    report = {"method": "plr", "policy_version": 3, "summary": {"buffer_size": 4, "buffer_fill": 1.0},
              "histograms": {"replays": zeros, "score": histogram(np.array([0.1, 0.2, 0.2]))},
              "top": [], "lineage": []}
    lines = format_report(report).splitlines()
    start = lines.index("replays histogram:")
    assert lines[start + 1].split() == ["0", "7", "#" * 30] and lines[start + 2] == "score histogram:"
    assert " .. " in lines[start + 3]  # scores keep their ranges
