"""`impulse train` refused before it trains (its training step does not fit in memory, its levels do not load)
takes back the run directory it created for a new run, and says so; a directory that was there before, a resumed
run's, and one holding checkpoints stay as they were (`deploy.runtime.run_dirs.remove_unstarted_run`)."""

from __future__ import annotations

from pathlib import Path

from impulse.deploy.cli import main
from impulse.deploy.runtime.run_dirs import remove_unstarted_run
from tests.support.paths import REPO

QUICK = REPO / "configs" / "quick-cpu.toml"
TINY = ["--config", str(QUICK), "ppo.num_envs=8", "ppo.num_steps=8", "ppo.num_minibatches=1", "network.width=16",
        "network.depth=1", "eval.attempts=0"]
"""The quick run, small."""


def test_a_refused_new_run_removes_its_run_directory(tmp_path: Path, capsys) -> None:
    """A refusal before training (here levels that do not load; a training step that does not fit is refused the
    same way, as a `RunError` from `FusedRun`) takes back the directory this command made, and says so."""
    run_dir = tmp_path / "runs" / "new"
    assert main(["train", f"run_dir={run_dir}", f"env.levels={tmp_path / 'missing.json'}", *TINY]) == 1
    err = capsys.readouterr().err
    assert "impulse train: env.levels: level set" in err, err
    assert f"removed {run_dir}, created for this run: nothing was trained" in err, err
    assert not run_dir.exists()
    assert run_dir.parent.is_dir()  # only the run directory goes, not the folders made above it


def test_a_refusal_keeps_a_directory_that_was_there_before(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "mine"
    run_dir.mkdir()
    (run_dir / "notes.txt").write_text("kept")
    assert main(["train", f"run_dir={run_dir}", f"env.levels={tmp_path / 'missing.json'}", *TINY]) == 1
    err = capsys.readouterr().err
    assert "env.levels" in err and "removed" not in err, err
    assert (run_dir / "notes.txt").read_text() == "kept"


def test_a_refused_resume_keeps_the_run_directory(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "earlier"
    run_dir.mkdir()
    (run_dir / "config.toml").write_text(QUICK.read_text())  # a run, as an earlier `impulse train` left it
    assert main(["train", "--resume", str(run_dir), f"env.levels={tmp_path / 'missing.json'}"]) == 1
    err = capsys.readouterr().err
    assert "env.levels" in err and "removed" not in err, err
    assert (run_dir / "config.toml").is_file()


def test_a_directory_with_checkpoints_is_never_removed(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints" / "5").mkdir(parents=True)
    assert not remove_unstarted_run(run_dir, run_dir / "checkpoints")
    assert (run_dir / "checkpoints" / "5").is_dir()
    assert remove_unstarted_run(tmp_path / "fresh", tmp_path / "fresh" / "checkpoints")  # nothing there: gone
