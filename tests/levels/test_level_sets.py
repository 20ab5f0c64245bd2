"""Level-set strings as `env.levels`, `eval.levels` and `impulse eval --levels` take them: Kinetix's own sets by
name, globs, and the group means Kinetix reports, so that our scores line up with its tables."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from engine.levels.sets import KINETIX_LEVELS_ENV, LevelSetError, kinetix_group, kinetix_levels_root, load_level_set
from engine.physics.sizes import SIZE_L, SIZE_S
from learner.run import format_scores, kinetix_groups

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared" / "kinetix-levels"
needs_levels = pytest.mark.skipif(not (SHARED / "s").is_dir(), reason=f"Kinetix's level files are not at {SHARED}")


@pytest.fixture
def two_levels(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A Kinetix level folder with two S files and one L file, found through the environment variable."""
    root = tmp_path / "kinetix-levels"
    for size, stem in (("s", "h0_weak_thrust"), ("s", "h4_thrust_aim"), ("l", "mjc_hopper")):
        (root / size).mkdir(parents=True, exist_ok=True)
        shutil.copy(SHARED / size / f"{stem}.json", root / size)
    (root / "m").mkdir()
    monkeypatch.setenv(KINETIX_LEVELS_ENV, str(root))
    return root


@needs_levels
def test_kinetix_sets_by_name(two_levels: Path) -> None:
    assert kinetix_levels_root() == two_levels
    names, levels = load_level_set("kinetix:s", SIZE_S)
    assert names == ["s/h0_weak_thrust", "s/h4_thrust_aim"]
    assert levels.roles.shape[0] == 2
    names, _ = load_level_set("kinetix:all", SIZE_L)
    assert names == ["s/h0_weak_thrust", "s/h4_thrust_aim", "l/mjc_hopper"]
    with pytest.raises(LevelSetError, match="kinetix:m"):
        load_level_set("kinetix:m", SIZE_S)  # the folder is empty
    with pytest.raises(LevelSetError, match="unknown Kinetix level set kinetix:xl"):
        load_level_set("kinetix:xl", SIZE_S)
    with pytest.raises(LevelSetError, match="mjc_hopper"):
        load_level_set("kinetix:l", SIZE_S)  # an L level does not fit S slots: the error names the file


@needs_levels
def test_the_shared_sets_have_kinetix_counts() -> None:
    for which, count in (("s", 10), ("m", 24)):
        names = load_level_set(f"{SHARED}/{which}", SIZE_L)[0]
        assert len(names) == count, names


def test_missing_kinetix_levels_say_how_to_provide_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(KINETIX_LEVELS_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(LevelSetError, match=KINETIX_LEVELS_ENV):
        load_level_set("kinetix:s", SIZE_S)


@needs_levels
def test_glob_patterns(two_levels: Path) -> None:
    names, _ = load_level_set(str(two_levels / "**" / "h*.json"), SIZE_S)
    assert names == ["h0_weak_thrust", "h4_thrust_aim"]
    with pytest.raises(LevelSetError, match="no .json level files match"):
        load_level_set(str(two_levels / "*.nothing"), SIZE_S)


def test_kinetix_groups_as_kinetix_logs_them() -> None:
    assert [kinetix_group(n) for n in ("s/h4_thrust_aim", "l/mjc_hopper", "m/arm_left", "l/hard_pinball")] == [
        "s_handmade", "l_mjc", "m_arm", "l_hard"]
    table = {name: {"solve_rate": rate, "mean_return": 0.0, "mean_length": 1.0}
             for name, rate in (("l/mjc_hopper", 0.5), ("l/mjc_walker", 0.0), ("l/h1_car_left", 1.0),
                                ("s/h0_weak_thrust", 0.25))}
    groups = kinetix_groups(table)
    assert groups == {"l_all": pytest.approx(0.5), "l_handmade": 1.0, "l_mjc": 0.25, "s_all": 0.25,
                      "s_handmade": 0.25}
    assert "l_mjc" in format_scores(table) and np.isclose(groups["l_all"], np.mean([0.5, 0.0, 1.0]))
    assert kinetix_groups({"h0_weak_thrust": table["s/h0_weak_thrust"]}) == {}  # not named by size: no groups
