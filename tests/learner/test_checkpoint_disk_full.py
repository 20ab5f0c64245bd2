"""A checkpoint that does not fit on the disk (`learner.checkpoint`): `save` raises one `DiskFullError` naming the
checkpoint and the space left, what orbax wrote of it is removed, the newest complete checkpoint stays the one a
restore takes (in this process and the next), and the same save succeeds once there is space.

Three ways to fill the disk: the writers' test hook (`engine.io_errors.limit_writes`), a background write that
fails as tensorstore fails on a full disk (its error, injected after the data is written), and where this runs
as root with `mount` allowed, a real 1.5 MiB tmpfs. Small trees, as in test_checkpoint_corruption."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import orbax.checkpoint as ocp
import pytest

from impulse.engine.io_errors import DiskFullError, lift_write_limits, limit_writes
from impulse.learner.checkpoint import ORBAX_TMP, Checkpointer
from impulse.learner.config import CheckpointConfig

SIZE = 4096
SIZE_PATTERN = r"\(\d+(\.\d)? [KMGT]?i?B free of \d+(\.\d)? [KMGT]?i?B\)"


def train_tree(step: int, size: int = SIZE) -> dict:
    rng = np.random.default_rng(step)
    return {"params": {"w": rng.standard_normal(size).astype(np.float32)}, "version": np.array(step, np.int32)}


def save(checkpoints: Checkpointer, step: int, size: int = SIZE) -> None:
    checkpoints.save(step, {"train": train_tree(step, size)}, {"update": step}, f"step = {step}\n")


def restored_step(directory: Path, size: int = SIZE) -> int:
    """What a new process resuming from `directory` restores (and checks that it holds that step's tree)."""
    with Checkpointer(directory) as fresh:
        restored = fresh.restore({"train": train_tree(0, size)})
    expected = train_tree(restored.step, size)["params"]["w"]
    np.testing.assert_array_equal(restored.items["train"]["params"]["w"], expected)
    return restored.step


def partials(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if ORBAX_TMP in p.name)


@pytest.fixture(autouse=True)
def no_write_limits():
    yield
    lift_write_limits()


def test_a_checkpoint_refused_by_a_full_disk_leaves_the_newest_one_in_place(tmp_path: Path) -> None:
    directory = tmp_path / "checkpoints"
    with Checkpointer(directory) as checkpoints:
        save(checkpoints, 1)
        save(checkpoints, 2)
        checkpoints.wait()
        limit_writes(tmp_path, sum(f.stat().st_size for f in tmp_path.rglob("*") if f.is_file()) + 100)
        with pytest.raises(DiskFullError, match=rf"^no space left on device writing {directory / '3'} {SIZE_PATTERN}$"):
            save(checkpoints, 3)
        assert checkpoints.latest_step() == 2 and partials(directory) == []
        assert checkpoints.restore({"train": train_tree(0)}).step == 2
        lift_write_limits()  # space freed: the same save goes through
        save(checkpoints, 3)
    assert restored_step(directory) == 3


def test_a_background_write_cut_short_by_a_full_disk_is_removed(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The data reaches the disk, then tensorstore fails as it does on ENOSPC: orbax leaves
    `3.orbax-checkpoint-tmp` with its files; the next save (or the close) says so in one line and removes it."""
    write = ocp.type_handlers.NumpyHandler._open_and_write
    full = {"on": False}

    async def fails_when_full(self, value, tspec, ts_context):
        await write(self, value, tspec, ts_context)
        if full["on"]:
            raise ValueError('RESOURCE_EXHAUSTED: Error writing "params.w/0" in OCDBT database: Failed to write '
                             "16384 bytes: No space left on device [os_error_code='28']")

    monkeypatch.setattr(ocp.type_handlers.NumpyHandler, "_open_and_write", fails_when_full)
    directory = tmp_path / "checkpoints"
    with Checkpointer(directory, CheckpointConfig(keep_last=5)) as checkpoints:
        save(checkpoints, 1)
        save(checkpoints, 2)
        checkpoints.wait()
        full["on"] = True
        save(checkpoints, 3)  # started in the background: its failure shows at the next save
        with pytest.raises(DiskFullError, match=rf"writing {directory / '3'} {SIZE_PATTERN}"):
            save(checkpoints, 4)
        assert partials(directory) == [] and checkpoints.all_steps() == [1, 2]
        assert restored_step(directory) == 2, "a resume never sees the partial checkpoint"
        # While the disk is short of room, a save waits for its write: the failure of 4 is raised by its own save.
        with pytest.raises(DiskFullError, match=rf"writing {directory / '4'} "):
            save(checkpoints, 4)
        assert partials(directory) == [] and checkpoints.all_steps() == [1, 2]
        full["on"] = False
        save(checkpoints, 4)
        full["on"] = True
        save(checkpoints, 5)
        with pytest.raises(DiskFullError, match=rf"writing {directory / '5'} "):
            checkpoints.close()  # the last write, found when the process closes its checkpoints
    assert partials(directory) == [] and restored_step(directory) == 4


@pytest.fixture
def tmpfs(tmp_path: Path):
    """A 1.5 MiB tmpfs at tmp_path/disk, where this runs as root and may mount; skipped elsewhere."""
    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1536k", "tmpfs", str(mount)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_checkpoints_on_a_real_full_tmpfs(tmpfs: Path) -> None:
    """600 KB checkpoints on a 1.5 MiB tmpfs: the third does not fit; it is removed and the second stays the
    newest; with one old checkpoint deleted by hand, the same save goes through."""
    directory = tmpfs / "checkpoints"
    size = 150_000
    with Checkpointer(directory, CheckpointConfig(keep_last=5)) as checkpoints:
        save(checkpoints, 1, size)
        save(checkpoints, 2, size)
        with pytest.raises(DiskFullError, match=rf"^no space left on device writing {directory / '3'} {SIZE_PATTERN}$"):
            save(checkpoints, 3, size)
        assert partials(directory) == [] and checkpoints.all_steps() == [1, 2]
        assert restored_step(directory, size) == 2
        subprocess.run(["rm", "-r", str(directory / "1")], check=True)
        save(checkpoints, 3, size)
    assert restored_step(directory, size) == 3
