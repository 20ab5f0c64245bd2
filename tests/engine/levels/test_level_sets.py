"""Level-set strings as `env.levels`, `eval.levels` and `impulse eval --levels` take them: Kinetix's own sets by
name, globs, and the group means Kinetix reports, so that our scores line up with its tables; sets holding bad
files name every bad file."""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from impulse.deploy.run_config import RunConfig
from impulse.engine.levels.sets import (
    KINETIX_LEVELS_ENV,
    MAX_LISTED_PROBLEMS,
    LevelSetError,
    kinetix_group,
    kinetix_levels_root,
    load_level_set,
)
from impulse.engine.physics.sizes import SIZE_L, SIZE_S
from impulse.learner.run import RunError, _eval_sets, _levels
from impulse.learner.scoring import format_scores, kinetix_groups
from tests.support.bad_level_files import good_level_text, write_bad_inputs
from tests.support.paths import SHARED_LEVELS

SHARED = SHARED_LEVELS
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


@pytest.fixture
def set_with_one_bad_file(tmp_path: Path) -> tuple[Path, Path]:
    """(a folder of two good level files and, in a subfolder, one PNG named like a level file; that PNG)."""
    folder = tmp_path / "set"
    (folder / "more").mkdir(parents=True)
    for name in ("a.json", "b.json"):
        (folder / name).write_text(good_level_text())
    bad, _ = write_bad_inputs(tmp_path / "bad")["PNG image"]
    shutil.copy(bad, folder / "more" / "picture.json")
    (folder / "more" / "not_a_file.json").mkdir()  # a folder named like a level file is skipped, not an error
    return folder, folder / "more" / "picture.json"


def test_set_with_one_bad_file_names_it(set_with_one_bad_file: tuple[Path, Path]) -> None:
    folder, bad = set_with_one_bad_file
    assert load_level_set(str(folder / "*.json"), SIZE_S)[0] == ["a", "b"]  # the good files alone load
    for source in (str(folder), str(folder / "**" / "*.json")):
        with pytest.raises(LevelSetError) as info:
            load_level_set(source, SIZE_S)
        message = str(info.value)
        assert message.startswith(f"level set {source!r}: 1 of 3 level files cannot be loaded:\n"), message
        assert message.splitlines()[1] == f"  {bad}: not a UTF-8 text file (byte 0x89 at offset 0): it looks like " \
                                          "a PNG image, not a level file"
        assert "a.json" not in message and "not_a_file" not in message


@pytest.mark.parametrize("case", ["latin-1 text", "random bytes", "PNG image", "empty file", "truncated JSON"])
def test_single_bad_file_set_gives_the_files_error(tmp_path: Path, case: str) -> None:
    path, expected = write_bad_inputs(tmp_path)[case]
    with pytest.raises(LevelSetError) as info:
        load_level_set(str(path), SIZE_S)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    assert all(part in message for part in expected), (expected, message)


def test_every_bad_file_of_a_set_is_named_up_to_a_limit(tmp_path: Path) -> None:
    written = write_bad_inputs(tmp_path)
    (tmp_path / "good.json").write_text(good_level_text())
    with pytest.raises(LevelSetError) as info:
        load_level_set(str(tmp_path / "*.json"), SIZE_S)  # the glob skips the folder named a_folder.json
    lines = str(info.value).splitlines()
    files = [path for path, _ in written.values() if path.is_file()]
    assert lines[0].endswith(f"{len(files)} of {len(files) + 1} level files cannot be loaded:")
    assert sorted(line.strip().partition(": ")[0] for line in lines[1:]) == sorted(map(str, files))
    for index in range(MAX_LISTED_PROBLEMS + 5):
        (tmp_path / f"empty_{index:02d}.json").touch()
    with pytest.raises(LevelSetError) as info:
        load_level_set(str(tmp_path), SIZE_S)
    lines = str(info.value).splitlines()
    assert len(lines) == MAX_LISTED_PROBLEMS + 2 and lines[-1] == f"  ... and {len(files) + 5} more problems"


def test_training_and_evaluation_level_errors_name_the_file(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path, _ = write_bad_inputs(tmp_path)["truncated JSON"]
    config = RunConfig()
    bad_env = dataclasses.replace(config, env=dataclasses.replace(config.env, levels=str(path)))
    with pytest.raises(RunError) as info:  # what `impulse train env.levels=FILE` prints after "impulse train: "
        _levels(bad_env, SIZE_S)
    assert str(info.value).startswith(f"env.levels: {path}: not valid JSON: Expecting value: line ")
    bad_eval = dataclasses.replace(config, eval=dataclasses.replace(config.eval, levels=str(path)))
    with caplog.at_level(logging.WARNING, logger="impulse.learner.run"):
        assert _eval_sets(bad_eval, SIZE_S, ["x"], None) is None
    assert f"no evaluation: eval.levels: level set '{path}': {path}: not valid JSON" in caplog.text
