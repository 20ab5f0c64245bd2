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
`export_tensorboard` (`impulse tensorboard RUN_DIR`), so both write the same points. tensorboardX is imported when
a sink opens and wandb (an optional extra) only when its project is set.
"""

from __future__ import annotations

import re
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from impulse.monitor.config import MonitorConfig
from impulse.monitor.runs import finite_number, read_metrics

if TYPE_CHECKING:
    from tensorboardX import SummaryWriter

TENSORBOARD_DIR = "tensorboard"
"""The event files' folder in a run directory (`tensorboard --logdir runs/` finds every run's)."""
STEP_COLUMN = "env_steps"
"""The column that is every scalar's step."""
WALL_TIME_COLUMN = "time_s"
"""The column that is every scalar's wall time."""
WANDB_INSTALL = "pip install 'impulse[wandb]'"
"""What installs the W&B client that `monitor.wandb_project` needs."""


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


def write_scalars(writer: SummaryWriter, record: Mapping[str, Any]) -> bool:
    """Write one metrics row to an event file: each of its `scalar_columns` at step `env_steps` and wall time
    `time_s`, then flush, so a killed process loses no more than `metrics.jsonl` does. False (nothing written) for
    a row without `env_steps`."""
    step = finite_number(record.get(STEP_COLUMN))
    if step is None:
        return False
    walltime = finite_number(record.get(WALL_TIME_COLUMN))
    for name, value in scalar_columns(record).items():
        writer.add_scalar(tensorboard_tag(name), value, global_step=int(step), walltime=walltime)
    writer.flush()
    return True


def tensorboard_writer(log_dir: Path, purge_after: int | None = None) -> SummaryWriter:
    """A new event file in `log_dir`. `purge_after`: the env steps a resumed run restarts from; TensorBoard then
    hides the points that earlier event files hold past that step (it keeps the one at it, as `metrics.jsonl`
    keeps the checkpoint's row)."""
    from tensorboardX import SummaryWriter

    log_dir.mkdir(parents=True, exist_ok=True)
    purge_step = None if purge_after is None else purge_after + 1
    # tensorboardX names a file by the second and the host, and overwrites one of the same name: a process
    # restarted within the second would erase its predecessor's. The nanoseconds keep names unique and in order.
    return SummaryWriter(str(log_dir), purge_step=purge_step, filename_suffix=f".{time.time_ns()}")


class TensorBoardSink:
    """A run's live event file: `write_scalars` for every row."""

    def __init__(self, log_dir: Path, resume_env_steps: int):
        self.writer = tensorboard_writer(log_dir, purge_after=resume_env_steps)

    def write(self, record: Mapping[str, Any]) -> None:
        write_scalars(self.writer, record)

    def close(self) -> None:
        self.writer.close()


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

    def write(self, record: Mapping[str, Any]) -> None:
        step = finite_number(record.get(STEP_COLUMN))
        if step is not None:
            self.run.log(scalar_columns(record), step=int(step))

    def close(self) -> None:
        self.run.finish()


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
