"""What a run directory holds, read from its folders alone (no JAX, no orbax), so that the launcher and the
command line can check it before anything heavy loads: the checkpoints themselves are `learner.checkpoint`'s."""

from __future__ import annotations

from pathlib import Path


def holds_checkpoints(directory: Path) -> bool:
    """Whether `directory` holds checkpoint steps, read from the folder alone (no orbax): a fresh run must not
    start there."""
    return directory.is_dir() and any(path.name.isdigit() for path in directory.iterdir())


def existing_run(run_dir: Path) -> str:
    """What to tell someone who starts a fresh run in a run directory that already holds checkpoints."""
    return f"{run_dir} already holds checkpoints: resume it with --resume, or choose another name"
