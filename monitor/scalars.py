"""The rows of `metrics.jsonl` as TensorBoard scalars and W&B history, where most RL researchers compare runs.

Every process that writes `metrics.jsonl` (the fused trainer, the learner) hands each row to the sinks opened here
as well (`deploy.runtime.runloop.run_loop`): TensorBoard event files under `<run_dir>/tensorboard/`
(`monitor.tensorboard`) and a Weights & Biases run (`monitor.wandb_project`). Each numeric column is one scalar
whose tag is the column's name, at step `env_steps`: env steps compare runs whose batches differ in size, where
update counts do not. The `update` column is one more scalar (hover a point to read its update); `env_steps` is
the step itself and `time_s` the point's wall time, so neither is a scalar of its own. Values that are not finite
(`null` in the file) and columns that are not numbers are left out.

A resumed run rewinds `metrics.jsonl` to its checkpoint; its event file then starts with TensorBoard's purge
marker (`purge_step`), so TensorBoard hides the points past the checkpoint that the previous process wrote and
this one redoes. W&B cannot drop points of a run it has synced, so each process start is a W&B run of its own,
grouped under the run's name: a resumed start logs from the checkpoint on, and where two overlap the newer one
holds what `metrics.jsonl` holds (docs/metrics.md).

`write_scalars` is the one function that turns a row into event-file scalars, used live and by
`export_tensorboard` (`impulse tensorboard RUN_DIR`), so both write the same points. The event file is written by
`EventFile`, synchronously, from tensorboardX's records (its protocol buffers and checksums): tensorboardX's own
`SummaryWriter` writes from a thread, which a full disk killed with a traceback, after which every row blocked on
its full queue. tensorboardX is imported when a sink opens and wandb (an optional extra) only when its project is
set.

A full disk (`engine.io_errors.DiskFullError`) never stops a run here: a sink that cannot write says so in one line
(the path and the space left), holds the rows it could not write (TensorBoard: up to HELD_BYTES of records, then
it leaves rows out and counts them) and writes them with the next row that fits; `close` says what could not be
written. metrics.jsonl, which the run loop waits on (`deploy.runtime.runloop`), keeps every row in any case, and
`impulse tensorboard --replace RUN_DIR` rewrites the event files from it.
"""

from __future__ import annotations

import logging
import os
import re
import socket
import struct
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from impulse.engine.io_errors import DiskFullError, append_whole, check_space, disk_full_error, writing
from impulse.monitor.config import MonitorConfig
from impulse.monitor.runs import finite_number, read_metrics

log = logging.getLogger(__name__)

TENSORBOARD_DIR = "tensorboard"
"""The event files' folder in a run directory (`tensorboard --logdir runs/` finds every run's)."""
STEP_COLUMN = "env_steps"
"""The column that is every scalar's step."""
WALL_TIME_COLUMN = "time_s"
"""The column that is every scalar's wall time."""
WANDB_INSTALL = "pip install 'impulse[wandb]'"
"""What installs the W&B client that `monitor.wandb_project` needs."""
HELD_BYTES = 16 * 2**20
"""Event records a TensorBoard sink holds while the disk is full (thousands of rows); rows past it are left out."""
FILE_VERSION = "brain.Event:2"


class ScalarSinkError(Exception):
    """A sink the configuration asks for cannot be opened; the message names the key and the remedy."""


class ScalarSink(Protocol):
    """Where a run's metrics rows go besides `metrics.jsonl`."""

    def write(self, record: Mapping[str, Any]) -> None: ...

    def close(self) -> None: ...


def scalar_columns(record: Mapping[str, Any]) -> dict[str, float | int]:
    """The columns of a metrics row that become scalars: every finite number but the step and wall-time columns."""
    columns = {}
    for key, value in record.items():
        number = finite_number(value)
        if number is not None and key not in (STEP_COLUMN, WALL_TIME_COLUMN):
            columns[key] = number
    return columns


def tensorboard_tag(name: str) -> str:
    """`name` as a TensorBoard tag: characters TensorBoard refuses (anything but letters, digits, `_`, `-`, `/`
    and `.`; `eval/kinetix:s` has one) become `_`, which tensorboardX would otherwise do with a log line per row."""
    return re.sub(r"[^-/\w.]", "_", name)


class EventFile:
    """One TensorBoard event file that this process writes, synchronously: `add_scalar` keeps a record in memory
    and `flush` appends every record kept in one write, whole or not at all (`engine.io_errors.append_whole`), so a
    failed flush (`DiskFullError` on a full disk) leaves the file as it was and the records for the next flush.
    Named as tensorboardX names its files, with the nanoseconds after: a process restarted within the second
    does not overwrite its predecessor's file. `purge_after`: the env steps a resumed run restarts from; the file
    then starts with TensorBoard's purge marker, which hides the points that earlier event files hold past that
    step (it keeps the one at it, as `metrics.jsonl` keeps the checkpoint's row)."""

    def __init__(self, log_dir: Path, purge_after: int | None = None):
        from tensorboardX.proto.event_pb2 import Event, SessionLog

        self._event = Event
        now = time.time()
        self.path = log_dir / f"events.out.tfevents.{int(now)}.{socket.gethostname()}.{time.time_ns()}"
        with writing(self.path):
            log_dir.mkdir(parents=True, exist_ok=True)
            self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_EXCL, 0o644)
        self._held: list[bytes] = []
        self.held_bytes = 0
        self._add(Event(wall_time=now, file_version=FILE_VERSION))
        if purge_after is not None:
            step = purge_after + 1
            self._add(Event(wall_time=now, step=step, file_version=FILE_VERSION))
            self._add(Event(wall_time=now, step=step, session_log=SessionLog(status=SessionLog.START)))

    def add_scalar(self, tag: str, value: float, global_step: int, walltime: float | None = None) -> None:
        """Keep one scalar point for the next `flush` (at `walltime`, default now)."""
        from tensorboardX.summary import scalar

        self._add(self._event(summary=scalar(tag, value), step=int(global_step),
                              wall_time=time.time() if walltime is None else walltime))

    def _add(self, event: Any) -> None:
        from tensorboardX.record_writer import masked_crc32c

        data = event.SerializeToString()
        header = struct.pack("Q", len(data))
        record = b"".join((header, struct.pack("I", masked_crc32c(header)), data,
                           struct.pack("I", masked_crc32c(data))))
        self._held.append(record)
        self.held_bytes += len(record)

    def flush(self) -> None:
        """Append the records kept since the last flush; `DiskFullError` (they stay kept) if they do not fit."""
        if not self._held:
            return
        if self._fd is None:
            raise ValueError(f"{self.path} is closed")
        data = b"".join(self._held)
        with writing(self.path):
            check_space(self.path, len(data))
            append_whole(self._fd, data)
        self._held.clear()
        self.held_bytes = 0

    def close(self) -> None:
        """Flush, then close the file (closed even when the flush fails, which raises)."""
        try:
            self.flush()
        finally:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None


def write_scalars(writer: EventFile, record: Mapping[str, Any]) -> bool:
    """Write one metrics row to an event file: each of its `scalar_columns` at step `env_steps` and wall time
    `time_s`, then flush, so a killed process loses no more than `metrics.jsonl` does. False (nothing written) for
    a row without `env_steps`. A full disk raises `DiskFullError` with the row's points kept for the next flush."""
    step = finite_number(record.get(STEP_COLUMN))
    if step is None:
        return False
    walltime = finite_number(record.get(WALL_TIME_COLUMN))
    for name, value in scalar_columns(record).items():
        writer.add_scalar(tensorboard_tag(name), value, global_step=int(step), walltime=walltime)
    writer.flush()
    return True


def tensorboard_writer(log_dir: Path, purge_after: int | None = None) -> EventFile:
    """A new event file in `log_dir` (`EventFile`; `purge_after`: a resumed run's env steps)."""
    return EventFile(log_dir, purge_after=purge_after)


class TensorBoardSink:
    """A run's live event file: `write_scalars` for every row. On a full disk it says so once, holds the rows'
    records (up to HELD_BYTES, then leaves rows out and counts them) and writes them with the next row that fits;
    it never raises for it (the module docstring)."""

    def __init__(self, log_dir: Path, resume_env_steps: int):
        self.log_dir = log_dir
        self.writer = tensorboard_writer(log_dir, purge_after=resume_env_steps)
        self.full: DiskFullError | None = None
        """Why the last flush failed (None once one succeeds)."""
        self.rows_left_out = 0
        try:
            self.writer.flush()  # the file's header (and purge marker) at once, as tensorboardX writes them
        except DiskFullError as err:
            log.error("TensorBoard: %s; its rows wait in memory until there is space (metrics.jsonl keeps them "
                      "too)", err)
            self.full = err

    def write(self, record: Mapping[str, Any]) -> None:
        if self.writer.held_bytes >= HELD_BYTES:
            self.rows_left_out += 1
            try:
                self.writer.flush()
            except DiskFullError:
                return
            self._written_again()
            return
        try:
            write_scalars(self.writer, record)
        except DiskFullError as err:
            if self.full is None:
                log.error("TensorBoard: %s; its rows wait in memory until there is space (metrics.jsonl keeps them "
                          "too)", err)
            self.full = err
            return
        self._written_again()

    def _written_again(self) -> None:
        if self.full is not None:
            left_out = f", {self.rows_left_out} left out" if self.rows_left_out else ""
            log.info("TensorBoard: the event file is written again (rows held while the disk was full are in it%s)",
                     left_out)
            self.full = None

    def close(self) -> None:
        try:
            self.writer.close()
        except DiskFullError as err:
            log.error("TensorBoard: the last rows could not be written to %s: %s (metrics.jsonl has them; "
                      "`impulse tensorboard --replace RUN_DIR` rewrites the event files from it)", self.writer.path,
                      err)
        if self.rows_left_out:
            log.warning("TensorBoard: %d rows were left out while the disk was full (metrics.jsonl has them)",
                        self.rows_left_out)


def require_wandb() -> None:
    """Raise `ScalarSinkError` naming the key and the install command when the W&B client cannot be imported, so
    that a run asking for W&B stops before it starts rather than when it opens its sinks."""
    try:
        import wandb  # noqa: F401
    except ImportError as err:
        raise ScalarSinkError(f"monitor.wandb_project is set but the W&B client cannot be imported ({err}); install "
                              f"it with `{WANDB_INSTALL}`, or leave monitor.wandb_project empty") from err


def require_tensorboard() -> None:
    """Raise `ScalarSinkError` naming the key when tensorboardX cannot be imported. It is one of Impulse's own
    dependencies, but a machine running the checkout with its own Python (a lent GPU, docs/gpu.md) may lack it."""
    try:
        import tensorboardX  # noqa: F401
    except ImportError as err:
        raise ScalarSinkError(f"monitor.tensorboard is on but tensorboardX cannot be imported ({err}); install "
                              "it with `pip install tensorboardX`, or set monitor.tensorboard=false") from err


def check_sinks(monitor: MonitorConfig) -> None:
    """Everything the configured sinks need, checked before a run starts (`ScalarSinkError`)."""
    if monitor.tensorboard:
        require_tensorboard()
    if monitor.wandb_project:
        require_wandb()


class WandbSink:
    """One W&B run per process start: the run's name as name and group, its resolved config as the W&B config,
    each row's `scalar_columns` logged at step `env_steps`. Its local files go to `<run_dir>/wandb/`."""

    def __init__(self, monitor: MonitorConfig, run_dir: Path, name: str, config: Mapping[str, Any],
                 resume_env_steps: int):
        require_wandb()
        import wandb

        self.run = wandb.init(project=monitor.wandb_project, entity=monitor.wandb_entity or None, name=name,
                              group=name, job_type="resume" if resume_env_steps else "train", config=dict(config),
                              dir=str(run_dir))
        self.files = run_dir / "wandb"
        self.rows_lost = 0

    def write(self, record: Mapping[str, Any]) -> None:
        step = finite_number(record.get(STEP_COLUMN))
        if step is None:
            return
        try:
            self.run.log(scalar_columns(record), step=int(step))
        except Exception as err:
            self._refused(err, "a row")

    def close(self) -> None:
        try:
            self.run.finish()
        except Exception as err:
            self._refused(err, "the end of the run")

    def _refused(self, err: Exception, what: str) -> None:
        """A full disk under the W&B client's files costs that row (said once; metrics.jsonl has it); any other
        error is the client's and is raised."""
        full = disk_full_error(self.files, err)
        if full is None:
            raise err
        self.rows_lost += 1
        if self.rows_lost == 1:
            log.error("W&B: %s could not be written: %s (metrics.jsonl has the rows W&B misses)", what, full)


def open_sinks(monitor: MonitorConfig, run_dir: Path, name: str, config: Mapping[str, Any],
               resume_env_steps: int) -> list[ScalarSink]:
    """The sinks `monitor` asks for, for a process that writes `<run_dir>/metrics.jsonl` and starts at
    `resume_env_steps` (0 for a new run)."""
    sinks: list[ScalarSink] = []
    if monitor.tensorboard:
        sinks.append(TensorBoardSink(run_dir / TENSORBOARD_DIR, resume_env_steps))
    if monitor.wandb_project:
        sinks.append(WandbSink(monitor, run_dir, name, config, resume_env_steps))
    return sinks


def export_tensorboard(metrics_path: Path, log_dir: Path) -> int:
    """Write the rows of an existing `metrics.jsonl` as one new event file in `log_dir`, with the same
    `write_scalars` a live run uses. Returns how many rows were written."""
    writer = tensorboard_writer(log_dir)
    try:
        return sum(write_scalars(writer, row) for row in read_metrics(metrics_path))
    finally:
        writer.close()


def event_files(log_dir: Path) -> Sequence[Path]:
    """The TensorBoard event files in `log_dir`, oldest name first."""
    return sorted(log_dir.glob("events.out.tfevents.*")) if log_dir.is_dir() else []
