"""A full disk under the run loop (`deploy.runtime.runloop`, docs/distributed.md "A full disk"), with a dummy
service (no JAX) and the writers' test hook (`engine.io_errors.limit_writes`) as the full disk: the loop says it in
one line naming the path and the space left, waits and retries, goes on once space is freed, and ends with every
metrics row once and every checkpoint whole; a stop while it waits tries the final checkpoint once and ends with
one line. Also the pieces: the message, whole-or-nothing appends, the log handler on a full disk, the hook that
ends a process on an uncaught `DiskFullError` with one line."""

from __future__ import annotations

import errno
import io
import json
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from impulse.bus.service import CycleReport, Progress
from impulse.deploy.runtime.log_setup import LogHandler, TextFormatter
from impulse.deploy.runtime.progress import MetricsFile, ProgressLine
from impulse.deploy.runtime.runloop import CheckpointNotWritten, LoopOptions, run_loop
from impulse.engine.io_errors import (
    DiskFullError,
    append_whole,
    check_space,
    disk_full_code,
    disk_full_message,
    lift_write_limits,
    limit_writes,
    writing,
)

FREE = r"\(\d+(\.\d)? [KMGT]?i?B free of \d+(\.\d)? [KMGT]?i?B\)"
FAST = {"disk_retry_s": 0.05, "disk_remind_s": 0.15}


@pytest.fixture(autouse=True)
def no_write_limits():
    yield
    lift_write_limits()


def used(folder: Path) -> int:
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


class CheckpointingService:
    """One update per cycle; `save` writes `checkpoints/<update>.json` (about `checkpoint_bytes`) through the test
    hook, whole or not at all, as a service's checkpointer does."""

    def __init__(self, run_dir: Path, updates: int, checkpoint_bytes: int = 200):
        self.run_dir = run_dir
        self.update = 0
        self.target = updates
        self.payload = "x" * checkpoint_bytes
        self.saves_tried: list[int] = []
        self.closed = 0

    def start(self) -> None:
        (self.run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)

    def progress(self) -> Progress:
        return Progress(total_env_steps=10 * self.target)

    def cycle(self) -> CycleReport:
        self.update += 1
        return CycleReport(env_steps=10, updates=1, metrics={"episodes": 1.0, "solved": 1.0, "return_sum": 1.0})

    def save(self, summary: dict[str, float]) -> None:
        self.saves_tried.append(self.update)
        path = self.run_dir / "checkpoints" / f"{self.update}.json"
        data = json.dumps({"update": self.update, "payload": self.payload})
        with writing(path):
            check_space(path, len(data))
            path.write_text(data)

    def finished(self) -> bool:
        return self.update >= self.target

    def close(self) -> None:
        self.closed += 1


def options(run_dir: Path, **extra) -> LoopOptions:
    return LoopOptions(metrics_path=run_dir / "metrics.jsonl", checkpoint_every=2,
                       progress=ProgressLine(1000, stream=io.StringIO()), **FAST, **extra)


def free_later(seconds: float) -> threading.Timer:
    """Free the disk (lift the hook's limit) after `seconds`, as a person deleting files would."""
    timer = threading.Timer(seconds, lift_write_limits)
    timer.start()
    return timer


def rows(run_dir: Path) -> list[int]:
    return [json.loads(line)["update"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def checkpoints(run_dir: Path) -> list[int]:
    found = []
    for path in sorted((run_dir / "checkpoints").iterdir(), key=lambda p: int(p.stem)):
        assert json.loads(path.read_text())["update"] == int(path.stem), f"{path} is not whole"
        found.append(int(path.stem))
    return found


def test_the_loop_waits_on_a_full_disk_and_goes_on_once_space_is_freed(tmp_path: Path, caplog) -> None:
    service = CheckpointingService(tmp_path, updates=8, checkpoint_bytes=0)
    service.start()
    limit_writes(tmp_path, 700)  # rows of about 95 bytes, checkpoints of 30: the row of update 7 does not fit
    timer = free_later(0.5)
    started = time.monotonic()
    with caplog.at_level(logging.INFO, logger="impulse.run"):
        summary = run_loop(service, options(tmp_path))
    timer.join()
    took = time.monotonic() - started
    assert took >= 0.5, "it waited for space"
    assert summary.seconds < took - 0.3, "the wait is left out of the run's rate"
    assert summary.updates == 8 and not summary.stopped and service.closed == 1
    assert rows(tmp_path) == list(range(1, 9)), "every row once: none lost, none twice"
    assert checkpoints(tmp_path) == [2, 4, 6, 8]
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1, errors
    assert re.match(rf"^the metrics row of update \d: no space left on device writing "
                    rf"{re.escape(str(tmp_path))}/metrics\.jsonl {FREE}; training waits", errors[0]), errors[0]
    said = caplog.text
    assert "still waiting for disk space" in said and "training goes on" in said
    assert "Traceback" not in said


def test_a_checkpoint_that_does_not_fit_pauses_the_loop_until_it_does(tmp_path: Path, caplog) -> None:
    service = CheckpointingService(tmp_path, updates=6, checkpoint_bytes=3000)
    service.start()
    limit_writes(tmp_path, 4000)  # the rows fit, the second checkpoint does not
    timer = free_later(0.4)
    with caplog.at_level(logging.INFO, logger="impulse.run"):
        summary = run_loop(service, options(tmp_path))
    timer.join()
    assert summary.updates == 6
    assert rows(tmp_path) == list(range(1, 7)) and checkpoints(tmp_path) == [2, 4, 6]
    assert service.saves_tried.count(4) > 1, "the checkpoint of update 4 was tried again"
    [error] = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert error.startswith(f"the checkpoint of update 4: no space left on device writing {tmp_path / 'checkpoints'}")


def test_a_stop_while_waiting_tries_the_final_checkpoint_once_and_ends_with_one_line(tmp_path: Path,
                                                                                     caplog) -> None:
    """Ctrl-C while the disk is full: the row waited on and the final checkpoint are tried once; neither fits,
    so the process ends with one line (a SystemExit: no traceback), its earlier checkpoints whole."""
    service = CheckpointingService(tmp_path, updates=50)
    service.start()
    limit_writes(tmp_path, 900)
    interrupt = threading.Timer(0.4, signal.raise_signal, (signal.SIGINT,))
    interrupt.start()
    with caplog.at_level(logging.INFO, logger="impulse.run"), pytest.raises(CheckpointNotWritten) as ended:
        run_loop(service, options(tmp_path))
    interrupt.join()
    message = str(ended.value.code)
    assert re.match(rf"^the final checkpoint \(update \d+\) could not be written: no space left on device writing "
                    rf"{re.escape(str(tmp_path))}/checkpoints/\d+\.json {FREE}; the checkpoints written before it are "
                    "intact$", message), message
    assert service.closed == 1 and service.update < 50
    assert service.saves_tried[-1] == service.update, "the final checkpoint was tried"
    kept = checkpoints(tmp_path)
    assert kept and kept[-1] < service.update
    assert rows(tmp_path) == list(range(1, len(rows(tmp_path)) + 1))
    assert "stopping while waiting for disk space" in caplog.text


def test_a_stop_while_waiting_ends_normally_when_the_final_checkpoint_fits(tmp_path: Path) -> None:
    service = CheckpointingService(tmp_path, updates=50, checkpoint_bytes=3000)
    service.start()
    limit_writes(tmp_path, 4000)
    def should_stop() -> bool:  # asks to stop once the loop has waited a little; the space comes back with it
        if service.saves_tried.count(4) > 1:
            lift_write_limits()
            return True
        return False

    summary = run_loop(service, options(tmp_path, should_stop=should_stop))
    assert summary.stopped and summary.updates == 4
    assert checkpoints(tmp_path) == [2, 4] and rows(tmp_path) == [1, 2, 3, 4]


def test_the_message_names_the_path_and_the_space_left(tmp_path: Path) -> None:
    limit_writes(tmp_path, 30 * 2**20)
    (tmp_path / "big").write_bytes(b"x" * (30 * 2**20 - 12 * 1024))
    assert disk_full_message(tmp_path / "metrics.jsonl") == \
        f"no space left on device writing {tmp_path / 'metrics.jsonl'} (12.0 KiB free of 30.0 MiB)"
    assert str(DiskFullError(tmp_path / "x", errno.EDQUOT)).startswith("disk quota exceeded writing")
    tensorstore = ValueError("RESOURCE_EXHAUSTED: Failed writing: ... [os_error_code='28']")
    wrapped = RuntimeError("save failed")
    wrapped.__cause__ = tensorstore
    assert disk_full_code(wrapped) == errno.ENOSPC and disk_full_code(OSError(errno.EIO, "x")) == errno.EIO
    assert disk_full_code(OSError(errno.ENOENT, "x")) is None and disk_full_code(ValueError("bad")) is None


def test_an_append_that_fails_part_way_leaves_the_file_as_it_was(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "metrics.jsonl"
    metrics = MetricsFile(path)
    metrics.write({"update": 1})
    real_write = os.write
    calls = {"n": 0}

    def short_then_full(fd: int, data) -> int:  # a full disk takes what fits, then refuses the rest
        calls["n"] += 1
        if calls["n"] == 1:
            return real_write(fd, bytes(data[:5]))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("impulse.engine.io_errors.os.write", short_then_full)
    with pytest.raises(DiskFullError, match=f"writing {path} "):
        metrics.write({"update": 2, "value": 0.5})
    monkeypatch.undo()
    assert path.read_text() == '{"update": 1}\n'
    metrics.write({"update": 2, "value": 0.5})
    metrics.close()
    assert [json.loads(line) for line in path.read_text().splitlines()] == [{"update": 1},
                                                                            {"update": 2, "value": 0.5}]
    with open(path, "ab") as raw:
        with pytest.raises(OSError):
            append_whole(raw.fileno() + 1000, b"x")  # a bad descriptor: the error passes unchanged


class FullDiskStream(io.StringIO):
    """A log file on a disk that is full while `full` is set."""

    def __init__(self, name: str) -> None:
        super().__init__()
        self.name = name
        self.full = True

    def write(self, text: str) -> int:
        if self.full:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(text)


def test_a_log_on_a_full_disk_drops_lines_quietly_and_says_so_once_it_can(tmp_path: Path, capsys) -> None:
    stream = FullDiskStream(str(tmp_path / "learner.log"))
    handler = LogHandler(stream)
    handler.setFormatter(TextFormatter())
    logger = logging.getLogger("tests.disk_full.log")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        for number in range(3):
            logger.warning("line %d", number)
        assert handler.lost == 3
        assert "Logging error" not in capsys.readouterr().err, "no traceback for a full disk"
        stream.full = False
        logger.warning("back")
    finally:
        logger.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and lines[1].endswith("back"), lines
    assert re.search(r"3 log line\(s\) were lost: no space left on device writing \S+learner\.log", lines[0])


@pytest.mark.heavy
def test_an_uncaught_disk_full_error_ends_a_process_with_one_line(tmp_path: Path) -> None:
    code = ("from impulse.deploy.runtime.log_setup import configure_logging; configure_logging(); "
            "from impulse.engine.io_errors import DiskFullError; "
            f"raise DiskFullError({str(tmp_path / 'metrics.jsonl')!r})")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert re.fullmatch(rf"impulse: no space left on device writing {re.escape(str(tmp_path))}/metrics\.jsonl "
                        rf"\(\S+ \S+ free of \S+ \S+\)\n", done.stderr), done.stderr
