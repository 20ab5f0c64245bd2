"""Reading back what a run wrote for TensorBoard (with TensorBoard's own `EventAccumulator`) and for W&B (the
records of an offline run's `.wandb` file, with W&B's own protobuf messages), and what each should hold according
to a `metrics.jsonl` (docs/metrics.md): every finite numeric column but `env_steps` (the step) and `time_s` (the
wall time)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

Points = dict[str, dict[int, float]]
"""tag -> step -> value."""


def metrics_rows(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def expected_points(rows: list[dict[str, Any]], precision: type = np.float32, tags: bool = True) -> Points:
    """What the rows of a metrics.jsonl become: tag -> env_steps -> value (TensorBoard keeps float32 and turns
    names into tags; W&B, `tags=False`, keeps the names)."""
    from impulse.monitor.scalars import tensorboard_tag

    points: Points = {}
    for row in rows:
        for key, value in row.items():
            if key in ("env_steps", "time_s") or isinstance(value, bool) or not isinstance(value, int | float):
                continue
            if math.isfinite(value):
                points.setdefault(tensorboard_tag(key) if tags else key, {})[row["env_steps"]] = float(precision(value))
    return points


def tensorboard_points(log_dir: Path) -> tuple[Points, dict[int, float]]:
    """The scalars TensorBoard shows for `log_dir` (tag -> step -> value) and each step's wall time."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(log_dir), size_guidance={"scalars": 0})
    events.Reload()
    points: Points = {}
    wall: dict[int, float] = {}
    for tag in events.Tags()["scalars"]:
        series = events.Scalars(tag)
        steps = [event.step for event in series]
        assert len(steps) == len(set(steps)), f"{tag}: a step shown twice: {steps}"
        points[tag] = {event.step: event.value for event in series}
        wall.update({event.step: event.wall_time for event in series})
    return points, wall


def wandb_records(path: Path) -> list[Any]:
    """The records of an offline W&B run's `run-*.wandb` file: W&B's header, then LevelDB-log framed protobufs
    (32 KiB blocks, each chunk with a 7-byte header: checksum, length, type FULL/FIRST/MIDDLE/LAST)."""
    from wandb.proto import wandb_internal_pb2

    data = path.read_bytes()
    assert data[:4] == b":W&B", path
    records, position, pending = [], 7, b""
    while position + 7 <= len(data):
        left = 32768 - position % 32768
        if left < 7:
            position += left
            continue
        length, kind = int.from_bytes(data[position + 4:position + 6], "little"), data[position + 6]
        if kind == 0:  # the zero padding at the end of a block
            position += left
            continue
        pending += data[position + 7:position + 7 + length]
        position += 7 + length
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            records.append(record)
            pending = b""
    return records


def wandb_run(wandb_dir: Path) -> tuple[Any, Points]:
    """The one offline run under `wandb_dir`: its run record (name, group, config) and its history as points."""
    files = list(wandb_dir.glob("offline-run-*/run-*.wandb"))
    assert len(files) == 1, files
    # W&B's core process writes the file: `finish` can return before it has written the last records (seen in
    # CI: the file read back without its run record), so wait for the closing `exit` record.
    deadline = time.monotonic() + 30
    while True:
        try:
            records = wandb_records(files[0])
        except Exception:  # noqa: BLE001 - a record still being written does not parse yet
            records = []
        if any(r.WhichOneof("record_type") == "exit" for r in records) or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    run, points = None, {}
    for record in records:
        kind = record.WhichOneof("record_type")
        if kind == "run":
            run = record.run
        elif kind == "history":
            for item in record.history.item:
                key = item.key or "/".join(item.nested_key)
                if not key.startswith("_"):
                    points.setdefault(key, {})[record.history.step.num] = json.loads(item.value_json)
    return run, points
