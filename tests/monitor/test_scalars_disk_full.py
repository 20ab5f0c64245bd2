"""The TensorBoard sink on a full disk (`monitor.scalars`): one clear line naming the event file and the space
left, no exception out of the sink, the rows held and written once there is space, each point once and the file
readable to its end (a write the disk cut short is cut off again, never left half a record)."""

from __future__ import annotations

import errno
import logging
import os
import re
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

from impulse.engine.io_errors import lift_write_limits, limit_writes
from impulse.monitor import scalars
from impulse.monitor.scalars import TensorBoardSink, event_files
from tests.support.scalars import tensorboard_points

FREE = r"\(\d+(\.\d)? [KMGT]?i?B free of \d+(\.\d)? [KMGT]?i?B\)"


def _row(update: int) -> dict:
    return {"update": update, "env_steps": 100 * update, "time_s": 1_800_000_000.0 + update, "solve_rate": 0.5,
            "episode_return": float(update)}


def _used(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


@pytest.fixture(autouse=True)
def no_write_limits():
    yield
    lift_write_limits()


def _check_file(log_dir: Path, updates: list[int]) -> None:
    [path] = event_files(log_dir)
    list(EventFileLoader(str(path)).Load())  # every record whole: the reader raises on a garbled one
    points, _ = tensorboard_points(log_dir)
    assert points["update"] == {100 * u: u for u in updates}, "every row once"


def test_a_full_disk_costs_the_sink_nothing_but_a_line(tmp_path: Path, caplog) -> None:
    log_dir = tmp_path / "tensorboard"
    sink = TensorBoardSink(log_dir, resume_env_steps=0)
    with caplog.at_level(logging.INFO, logger="impulse.monitor.scalars"):
        for update in (1, 2, 3):
            sink.write(_row(update))
        limit_writes(tmp_path, _used(tmp_path))  # the disk is full from here on
        for update in (4, 5, 6):
            sink.write(_row(update))  # never raises
        assert sink.full is not None and sink.writer.held_bytes > 0
        lift_write_limits()
        sink.write(_row(7))
        sink.close()
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1, errors
    assert re.match(rf"^TensorBoard: no space left on device writing {re.escape(str(log_dir))}/events\.out\.tfevents"
                    rf"\S+ {FREE}; its rows wait in memory", errors[0]), errors[0]
    assert "written again" in caplog.text
    _check_file(log_dir, list(range(1, 8)))


def test_a_write_the_disk_cut_short_leaves_no_half_record(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log_dir = tmp_path / "tensorboard"
    sink = TensorBoardSink(log_dir, resume_env_steps=0)
    sink.write(_row(1))
    real_write = os.write
    calls: list[int] = []

    def takes_a_little(fd: int, data) -> int:  # a full disk takes what fits (ten bytes), then refuses the rest
        calls.append(len(data))
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, bytes(data[:10]))

    monkeypatch.setattr("impulse.engine.io_errors.os.write", takes_a_little)
    sink.write(_row(2))
    assert sink.full is not None and len(calls) == 2
    monkeypatch.undo()
    sink.write(_row(3))
    sink.close()
    _check_file(log_dir, [1, 2, 3])


def test_rows_past_what_it_holds_are_left_out_and_said(tmp_path: Path, caplog,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(scalars, "HELD_BYTES", 300)
    log_dir = tmp_path / "tensorboard"
    sink = TensorBoardSink(log_dir, resume_env_steps=0)
    sink.write(_row(1))
    limit_writes(tmp_path, _used(tmp_path))
    with caplog.at_level(logging.INFO, logger="impulse.monitor.scalars"):
        for update in range(2, 12):
            sink.write(_row(update))
        assert sink.rows_left_out > 0
        sink.close()  # still full: it says what could not be written, and does not raise
    assert "the last rows could not be written" in caplog.text and "rows were left out" in caplog.text
    lift_write_limits()
    [path] = event_files(log_dir)
    list(EventFileLoader(str(path)).Load())
