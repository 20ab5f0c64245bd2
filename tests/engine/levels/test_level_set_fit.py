"""Level sets and the configured size: a set of several levels leaves out those that do not fit
with one warning naming each and the size it needs, the same for every command (they all load through
`load_level_set`); a set of which none fits, or a level named on its own, is refused."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest

from impulse.engine.levels import handmade
from impulse.engine.levels.kinetix_json import LevelDoesNotFit, load_kinetix_level
from impulse.engine.levels.level import Level
from impulse.engine.levels.sets import LevelSetError, load_level_set, size_needed
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes
from impulse.learner.scoring import load_level_sets
from tests.support.paths import SHARED_LEVELS

LOGGER = "impulse.engine.levels.sets"
needs_levels = pytest.mark.skipif(not (SHARED_LEVELS / "s").is_dir(),
                                  reason=f"Kinetix's level files are not at {SHARED_LEVELS}")


@pytest.fixture
def mixed(tmp_path: Path) -> Path:
    """A folder of one S, one M and one L Kinetix level."""
    folder = tmp_path / "mixed"
    folder.mkdir()
    for size, stem in (("s", "h0_weak_thrust"), ("m", "h0_unicycle"), ("l", "mjc_hopper")):
        shutil.copy(SHARED_LEVELS / size / f"{stem}.json", folder)
    return folder


def warnings_of(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == LOGGER and r.levelno == logging.WARNING]


@needs_levels
def test_a_set_of_several_sizes_leaves_out_what_does_not_fit(
    mixed: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger=LOGGER)
    names, levels = load_level_set(str(mixed), SIZE_S)
    assert names == ["h0_weak_thrust"] and levels.roles.shape == (1, SIZE_S.num_bodies)
    assert warnings_of(caplog) == [f"level set {str(mixed)!r}: 2 of 3 levels do not fit size s and are left out: "
                                   "h0_unicycle (needs m), mjc_hopper (needs l)"]
    caplog.clear()
    names, _ = load_level_set(str(mixed / "*.json"), SIZE_S)  # a glob the same
    assert names == ["h0_weak_thrust"] and len(warnings_of(caplog)) == 1
    caplog.clear()
    names, levels = load_level_set(str(mixed), SIZE_L)  # at L every level fits: all kept, no warning
    assert names == ["h0_unicycle", "h0_weak_thrust", "mjc_hopper"] and levels.roles.shape[0] == 3
    assert warnings_of(caplog) == []


@needs_levels
def test_one_level_named_on_its_own_or_none_fitting_is_refused(tmp_path: Path, mixed: Path) -> None:
    with pytest.raises(LevelSetError, match=r"h0_unicycle.json: too large for the size: the file has 6 polygons"):
        load_level_set(str(mixed / "h0_unicycle.json"), SIZE_S)
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(mixed / "mjc_hopper.json", alone)
    with pytest.raises(LevelSetError) as info:
        load_level_set(str(alone), SIZE_M)
    assert str(info.value) == f"level set {str(alone)!r}: its one level, mjc_hopper (needs l), does not fit size m"
    shutil.copy(mixed / "h0_unicycle.json", alone)
    with pytest.raises(LevelSetError) as info:
        load_level_sets(str(alone), SIZE_S)  # named once, not twice, through the evaluation loader
    assert str(info.value) == (f"level set {str(alone)!r}: none of its 2 levels fits size s: h0_unicycle (needs m), "
                               "mjc_hopper (needs l)")
    with pytest.raises(LevelDoesNotFit) as error:
        load_kinetix_level(mixed / "mjc_hopper.json", SIZE_S)
    assert error.value.needs.num_polygons == 12 and size_needed(error.value.needs) == "l"


def test_hand_made_set_leaves_out_larger_levels_and_refuses_named_ones(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The registry's sizes decide; building is replaced by one stand-in level (building the designs eagerly costs
    compiles, and test_handmade builds them)."""
    with pytest.raises(LevelSetError, match=r"^hand-made level\(s\) l_claw \(needs l\) too large for size s$"):
        load_level_set("handmade:s_lander,l_claw", SIZE_S)
    built: list[str] = []
    stand_in = load_kinetix_level(handmade.level_file("s_lander"), SIZE_S).level  # its exported file: no building

    def build(name: str, sizes: SceneSizes) -> Level:
        built.append(name)
        return stand_in

    monkeypatch.setattr(handmade, "build", build)
    caplog.set_level(logging.WARNING, logger=LOGGER)
    names, _ = load_level_set("handmade", SIZE_S)
    small = [name for name in handmade.names() if handmade.LEVELS[name].size == "s"]
    assert names == built == small and len(small) == 5
    others = [f"{name} (needs {handmade.LEVELS[name].size})" for name in handmade.names() if name not in small]
    assert warnings_of(caplog) == [f"level set 'handmade': 9 of 14 levels do not fit size s and are left out: "
                                   f"{', '.join(others)}"]
    assert "m_car_bump (needs m)" in others and "l_claw (needs l)" in others


def test_the_size_a_level_needs() -> None:
    assert [size_needed(sizes) for sizes in (SIZE_S, SIZE_M, SIZE_L)] == ["s", "m", "l"]
    assert size_needed(SceneSizes(num_polygons=6, num_circles=2, num_joints=1, num_thrusters=1)) == "m"
    assert size_needed(SceneSizes(num_polygons=13)).startswith("custom (13 polygons incl. 4 arena")
