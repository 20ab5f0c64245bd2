"""Helpers for the distributed tests: a real `impulse launch` in a subprocess, its children found by command
line, their statuses read from the bus, their memory read from /proc."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from impulse.bus.codec import Rejected
from impulse.bus.config import BusConfig
from impulse.bus.keys import OPERATOR
from impulse.bus.session import Bus
from impulse.bus.status import read_status
from tests.support.paths import REPO

QUICK_LAUNCH = REPO / "configs" / "quick-launch.toml"
SMALL_BATCH = ("ppo.num_envs=32", "ppo.num_steps=32", "ppo.num_minibatches=2")
"""Overrides for tests of the runtime rather than of learning: a quarter of quick-launch's batch, so that the
steady state of a run (actors rolling out, the learner updating) costs a quarter of the CPU. Those tests share
the programs compiled for it through the compilation cache (test_fault_injection.py's processes run
test_launch_backpressure.py's programs)."""
TINY_BATCH = ("ppo.num_envs=8", "ppo.num_steps=8", "ppo.num_minibatches=1")
"""Overrides for tests of the bus and the processes around the learning: 8 envs x 8 steps. The actor of
tests/actors/test_actor_credits.py and those test_multi_host.py starts run one program (the compilation cache's)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_launch(run_dir: Path, port: int, *overrides: str) -> tuple[subprocess.Popen, Path]:
    """`impulse launch` on the quick config in `run_dir`, its own hub port; output to run_dir.parent/launch.log."""
    log_path = run_dir.parent / f"{run_dir.name}-launch.log"
    env = {**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache"), "PYTHONUNBUFFERED": "1"}
    command = [sys.executable, "-m", "impulse.deploy.cli", "launch", "--config", str(QUICK_LAUNCH),
               "--status-every", "2", f"run_dir={run_dir}", f"name={run_dir.name}", f"bus.hub=tcp/127.0.0.1:{port}",
               *overrides]
    with log_path.open("wb") as out:
        process = subprocess.Popen(command, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    return process, log_path


def stop_launch(launch: subprocess.Popen, run_dir: Path,
                roles: tuple[str, ...] = ("learner", "actor", "curriculum", "evaluator", "recorder"),
                grace_s: float = 120.0) -> None:
    """Clean up after a launch test, whatever happened: SIGTERM the launcher (killing it after `grace_s`), then
    SIGKILL any service process of the run still alive."""
    if launch.poll() is None:
        launch.send_signal(signal.SIGTERM)
        try:
            launch.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            launch.kill()
    for role in roles:
        for pid in service_pids(run_dir, role):
            os.kill(pid, signal.SIGKILL)


def wait_for(condition: Callable[[], Any], timeout_s: float, what: str, process: subprocess.Popen | None = None,
             log_path: Path | None = None) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if process is not None and process.poll() is not None:
            raise AssertionError(f"launcher exited ({process.returncode}) while waiting for {what}\n{tail(log_path)}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}\n{tail(log_path)}")
        time.sleep(0.2)


def tail(path: Path | None, lines: int = 60) -> str:
    if path is None or not path.exists():
        return ""
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])


def metrics(run_dir: Path) -> list[dict[str, Any]]:
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def last_update(run_dir: Path) -> int:
    records = metrics(run_dir)
    return int(records[-1]["update"]) if records else 0


def service_pids(run_dir: Path, role: str, index: int | None = None) -> list[int]:
    """PIDs of `impulse <role> --run run_dir [--index N]` processes, from /proc."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            words = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        args = [w.decode(errors="replace") for w in words if w]
        if role in args and str(run_dir) in args and "impulse.deploy.cli" in args:
            if index is None or ("--index" in args and args[args.index("--index") + 1] == str(index)):
                found.append(int(entry.name))
    return found


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for {pid}")


class StatusWatcher:
    """The latest status of every process of a run, read from the bus like the launcher's display."""

    def __init__(self, run: str, port: int, config: BusConfig | None = None):
        self.run = run
        self.bus = Bus(config or BusConfig(hub=f"tcp/127.0.0.1:{port}"), run, OPERATOR, "watcher")
        self.inbox = self.bus.inbox(self.bus.keys.status_pattern(), 256, drop_oldest=True)
        self.latest: dict[str, dict[str, Any]] = {}

    def poll(self) -> dict[str, dict[str, Any]]:
        for received in self.inbox.poll():
            try:
                heard = read_status(received, self.bus.keys)
            except Rejected:
                continue
            self.latest[heard.ident] = heard.status
        return self.latest

    def close(self) -> None:
        self.bus.close()
