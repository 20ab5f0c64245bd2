"""How far behind the live viewer is: from a process's log call to the data reaching a viewer of the run.

Runs a real `impulse launch --record FILE` (learner, actors, and the headless Rerun server that the launcher
starts, whose recording client is connected the way a viewer is) and reads FILE while the run goes on. Every row
Rerun logs carries `log_time`, the wall clock of the log call in the process that logged it; the latency of a row
is the start of the read of FILE that first finds it minus its `log_time`. Besides the path SDK -> server ->
viewer it counts the recording client's file writes and up to one polling period (`--poll`); a row written while
a read runs may be found by it, so each latency is low by at most that read's time (reported as `read_s_*`).

Optionally `--busy N` processes spin on the CPU beside the run, for a loaded machine.

Prints one JSON line per family of entities (`rollouts`, `metrics`, `curriculum`, ...): rows seen, latency p50,
p90, p99 and max, and the p50 over the first and the last third of the run (a latency that grows means a
backlog).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from impulse.benchmarks._harness import REPO, emit, progress

DEFAULT_CONFIG = REPO / "configs" / "quick-launch.toml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spin() -> None:
    while True:
        pass


def new_rows(path: Path, seen: set[bytes]) -> list[tuple[str, float]]:
    """(family, log_time in seconds) of every row of the recording at `path` not in `seen` (row ids), which it
    adds to."""
    from rerun.chunk import RrdReader

    found: list[tuple[str, float]] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a recording still being written has no footer yet
        try:
            chunks = list(RrdReader(path).stream())
        except (ValueError, RuntimeError):  # no recording yet, or a frame half written: read it next time
            return []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        if "log_time" not in batch.schema.names:
            continue
        family = chunk.entity_path.strip("/").split("/", 1)[0]
        row_ids = batch.column("rerun.controls.RowId").to_pylist()
        times = batch.column("log_time").cast("int64").to_numpy(zero_copy_only=False)
        for row_id, logged in zip(row_ids, times):
            key = bytes(str(row_id), "utf8")
            if key not in seen:
                seen.add(key)
                found.append((family, logged / 1e9))
    return found


def summarise(samples: dict[str, list[tuple[float, float]]], started: float, ended: float) -> list[dict[str, Any]]:
    """Per family: latency percentiles over the run, and the median over its first and last third."""
    rows = []
    third = (ended - started) / 3
    for family, pairs in sorted(samples.items()):
        found_at = np.asarray([at for at, _ in pairs])
        latency = np.asarray([lat for _, lat in pairs])
        early = latency[found_at < started + third]
        late = latency[found_at >= ended - third]
        rows.append({
            "family": family,
            "rows": int(latency.size),
            "latency_p50_s": round(float(np.percentile(latency, 50)), 3),
            "latency_p90_s": round(float(np.percentile(latency, 90)), 3),
            "latency_p99_s": round(float(np.percentile(latency, 99)), 3),
            "latency_max_s": round(float(latency.max()), 3),
            "p50_first_third_s": round(float(np.median(early)), 3) if early.size else None,
            "p50_last_third_s": round(float(np.median(late)), 3) if late.size else None,
        })
    return rows


def run(config: Path, overrides: list[str], seconds: float, poll_s: float, busy: int, keep: Path | None) -> int:
    workdir = keep or Path(tempfile.mkdtemp(prefix="viewer-latency-"))
    workdir.mkdir(parents=True, exist_ok=True)
    recording, run_dir = workdir / "run.rrd", workdir / "run"
    command = [sys.executable, "-m", "impulse.deploy.cli", "launch", "--config", str(config), f"run_dir={run_dir}",
               "name=viewer-latency", f"bus.hub=tcp/127.0.0.1:{_free_port()}",
               f"monitor.url=rerun+http://127.0.0.1:{_free_port()}/proxy", f"monitor.web_port={_free_port()}",
               "total_env_steps=100000000", "--record", str(recording), *overrides]
    spinners = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(busy)]
    for spinner in spinners:
        spinner.start()
    log = (workdir / "launch.log").open("wb")
    launch = subprocess.Popen(command, cwd=REPO, stdout=log, stderr=subprocess.STDOUT,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    samples: dict[str, list[tuple[float, float]]] = {}
    seen: set[bytes] = set()
    load: list[float] = []
    reads: list[float] = []  # seconds each read of the recording took
    started = ended = 0.0
    try:
        progress(f"launch with --record {recording}; waiting for the first rows ...")
        deadline = time.monotonic() + 600
        while not recording.exists() or not new_rows(recording, seen):  # rows before this are not counted
            if launch.poll() is not None or time.monotonic() > deadline:
                progress(f"the launch ended or never recorded; see {workdir / 'launch.log'}")
                return 1
            time.sleep(1)
        started = time.time()
        while time.time() - started < seconds and launch.poll() is None:
            time.sleep(poll_s)
            # A row found by this read was in the file by its end, and those written while it reads are found
            # too: latency is taken from the read's start (a lower bound by at most the read's time, reported).
            now = time.time()
            for family, logged in new_rows(recording, seen):
                samples.setdefault(family, []).append((now, now - logged))
            reads.append(time.time() - now)
            load.append(os.getloadavg()[0])
        ended = time.time()
    finally:
        if launch.poll() is None:
            launch.send_signal(signal.SIGINT)
            try:
                launch.wait(timeout=240)
            except subprocess.TimeoutExpired:
                launch.kill()
        for spinner in spinners:
            spinner.terminate()
        log.close()
    for row in summarise(samples, started, ended):
        emit({**row, "poll_s": poll_s, "busy_processes": busy, "seconds": round(ended - started, 1),
              "load_1min_mean": round(float(np.mean(load)), 2) if load else None, "cpus": os.cpu_count(),
              "read_s_mean": round(float(np.mean(reads)), 3) if reads else None,
              "read_s_max": round(float(np.max(reads)), 3) if reads else None})
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench viewer_latency", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--seconds", type=float, default=120.0, help="how long to measure once rows arrive")
    parser.add_argument("--poll", type=float, default=1.0, help="seconds between reads of the recording")
    parser.add_argument("--busy", type=int, default=0, help="processes spinning on the CPU beside the run")
    parser.add_argument("--keep", type=Path, help="keep the run and the recording in this folder")
    parser.add_argument("overrides", nargs="*", help="key=value overrides of the run config")
    args = parser.parse_args(argv)
    return run(args.config, args.overrides, args.seconds, args.poll, args.busy, args.keep)


if __name__ == "__main__":
    raise SystemExit(main())
