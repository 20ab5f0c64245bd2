"""`--checkpoint PATH` names a run directory (its newest checkpoint) or one checkpoint's folder, read the same way
by `impulse eval`, `impulse export`, Studio's agents and `impulse bench open_loop --agent`
(`deploy.runtime.run_dirs.locate_checkpoint`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from impulse.deploy.runtime.run_dirs import locate_checkpoint


def _run(path: Path) -> Path:
    (path / "checkpoints" / "25").mkdir(parents=True)
    (path / "config.toml").write_text('name = "r"\n')
    return path


def test_a_run_directory_means_its_newest_checkpoint(tmp_path: Path) -> None:
    run = _run(tmp_path / "run")
    assert locate_checkpoint(run) == (run, None)


def test_a_checkpoint_folder_names_its_step(tmp_path: Path) -> None:
    run = _run(tmp_path / "run")
    assert locate_checkpoint(run / "checkpoints" / "25") == (run, 25)


def test_a_run_directory_named_by_a_number_is_not_a_step(tmp_path: Path) -> None:
    run = _run(tmp_path / "900")
    assert locate_checkpoint(run) == (run, None)


def test_no_config_anywhere_is_an_error_naming_the_path(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no config.toml in .*nowhere"):
        locate_checkpoint(tmp_path / "nowhere" / "checkpoints" / "3")
