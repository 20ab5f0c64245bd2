"""Damage done to checkpoints on disk by the tests of what survives it: the largest file of an item (its arrays'
bytes, for trees large enough to get a data file of their own) cut to half its length, as a disk that filled up
or a copy interrupted midway leaves it."""

from __future__ import annotations

from pathlib import Path


def truncate(path: Path) -> None:
    """Cut `path` to half its length."""
    data = path.read_bytes()
    assert len(data) > 1, path
    path.write_bytes(data[: len(data) // 2])


def largest_file(directory: Path) -> Path | None:
    """The largest file under `directory`, or None when there is none."""
    files = [p for p in directory.rglob("*") if p.is_file()] if directory.is_dir() else []
    return max(files, key=lambda p: p.stat().st_size) if files else None


def corrupt_newest(directory: Path, item: str) -> int | None:
    """Truncate the largest file of `item` in the newest checkpoint under `directory`; its step, or None when there
    is no checkpoint (with files for `item`) yet."""
    steps = sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit()) if directory.is_dir() else []
    target = largest_file(directory / str(steps[-1]) / item) if steps else None
    if target is None:
        return None
    truncate(target)
    return steps[-1]
