"""A synthetic fleet of actors against a real curriculum service: level requests from N actors, their latency.

Starts a real `impulse curriculum serve` (random levels, the config's curriculum and batch size) behind a zenoh
hub on loopback, then for each fleet size N plays N actors as zenoh sessions spread over a few processes. Each
actor asks for a level batch (`levels_sample`, one batch of `ppo.num_envs` levels, as a real actor does before
every rollout) every `--period` seconds, starting at a random phase, and times the answer. Per N, one JSON line:
requests answered per second, latency p50/p90/p99/max, requests that got no answer in time, and the service's
resident memory.

Only the curriculum's side of a fleet is driven: the learner's ingest of trajectory frames is not measured here.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from impulse.benchmarks._harness import REPO, emit, progress

DEFAULT_CONFIG = REPO / "configs" / "quick-launch.toml"
RUN = "fleet"
TIMEOUT_S = 10.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def play_actors(hub: str, names: list[str], batch: int, period_s: float, seconds: float, out: Any) -> None:
    """One fleet process: an actor session per name, each asking for a level batch every `period_s` for
    `seconds`; puts (answered latencies, unanswered count) on `out`."""
    from impulse.bus.config import BusConfig
    from impulse.bus.keys import ACTOR
    from impulse.bus.session import Bus

    config = BusConfig(connect=(hub,), hub=hub)
    sessions = [Bus(config, RUN, ACTOR, name) for name in names]
    for session in sessions:
        session.__enter__()
    for session in sessions:
        session.wait_queryable(session.keys.levels_sample, 60)
    latencies: list[float] = []
    unanswered = 0
    lock = threading.Lock()
    stop_at = time.monotonic() + seconds

    def actor(session: Any) -> None:
        nonlocal unanswered
        next_at = time.monotonic() + random.uniform(0, period_s)
        while True:
            time.sleep(max(0.0, next_at - time.monotonic()))
            if time.monotonic() >= stop_at:
                return
            started = time.perf_counter()
            replies = session.get(session.keys.levels_sample, parameters=f"n={batch}", timeout_s=TIMEOUT_S)
            took = time.perf_counter() - started
            with lock:
                if replies:
                    latencies.append(took)
                else:
                    unanswered += 1
            next_at += period_s

    threads = [threading.Thread(target=actor, args=(s,), daemon=True) for s in sessions]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for session in sessions:
        session.__exit__(None, None, None)
    out.put((latencies, unanswered))


def measure(hub: str, service_pid: int, actors: int, processes: int, batch: int, period_s: float,
            seconds: float) -> dict[str, Any]:
    context = multiprocessing.get_context("spawn")
    out = context.Queue()
    names = [f"actor-{i}" for i in range(actors)]
    shares = [names[i::processes] for i in range(min(processes, actors))]
    workers = [context.Process(target=play_actors, args=(hub, share, batch, period_s, seconds, out))
               for share in shares]
    for worker in workers:
        worker.start()
    rss = []
    results = []
    while len(results) < len(workers):
        try:
            results.append(out.get(timeout=2.0))
        except Exception:  # noqa: BLE001 - queue.Empty: sample the service's memory meanwhile
            rss.append(_rss_mib(service_pid))
    for worker in workers:
        worker.join(timeout=30)
    latencies = np.asarray([lat for got, _ in results for lat in got]) * 1000
    unanswered = sum(missing for _, missing in results)
    return {
        "actors": actors,
        "fleet_processes": len(workers),
        "period_s": period_s,
        "batch_levels": batch,
        "offered_per_s": round(actors / period_s, 1),
        "answered_per_s": round(latencies.size / seconds, 1),
        "unanswered": int(unanswered),
        "latency_p50_ms": round(float(np.percentile(latencies, 50)), 1) if latencies.size else None,
        "latency_p90_ms": round(float(np.percentile(latencies, 90)), 1) if latencies.size else None,
        "latency_p99_ms": round(float(np.percentile(latencies, 99)), 1) if latencies.size else None,
        "latency_max_ms": round(float(latencies.max()), 1) if latencies.size else None,
        "service_rss_mib_max": round(max(rss), 1) if rss else round(_rss_mib(service_pid), 1),
        "cpus": os.cpu_count(),
    }


def run(config: Path, overrides: list[str], sizes: list[int], processes: int, period_s: float,
        seconds: float) -> int:
    from impulse.bus.config import BusConfig
    from impulse.bus.keys import OPERATOR
    from impulse.bus.session import Bus
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig

    overrides = ["env.levels=random", *overrides]
    batch = resolve_config(RunConfig, config, overrides).ppo.num_envs
    hub = f"tcp/127.0.0.1:{_free_port()}"
    workdir = Path(tempfile.mkdtemp(prefix="fleet-"))
    with Bus(BusConfig(hub=hub), RUN, OPERATOR, "fleet-hub", listen=True) as bus:
        log = (workdir / "curriculum.log").open("wb")
        service = subprocess.Popen(
            [sys.executable, "-m", "impulse.deploy.cli", "curriculum", "serve", "--config", str(config),
             f"--connect={hub}", f"run_dir={workdir / 'run'}", f"name={RUN}", f"bus.hub={hub}", *overrides],
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            progress(f"curriculum service starting (log {workdir / 'curriculum.log'}) ...")
            deadline = time.monotonic() + 600
            while not bus.wait_queryable(bus.keys.levels_sample, 5):
                if service.poll() is not None or time.monotonic() > deadline:
                    progress(f"the curriculum service never answered; see {workdir / 'curriculum.log'}")
                    return 1
            # The service declares its queryable before it compiles: the first answer waits for the compile.
            if not bus.get(bus.keys.levels_sample, parameters=f"n={batch}", timeout_s=600):
                progress(f"no first answer from the curriculum service; see {workdir / 'curriculum.log'}")
                return 1
            for actors in sizes:
                progress(f"{actors} actors, one request each every {period_s} s, for {seconds} s ...")
                row = measure(hub, service.pid, actors, processes, batch, period_s, seconds)
                emit(row)
        finally:
            service.send_signal(signal.SIGINT)
            try:
                service.wait(timeout=60)
            except subprocess.TimeoutExpired:
                service.kill()
            log.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench fleet", description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 16, 64, 128, 256],
                        help="fleet sizes to measure, one after another")
    parser.add_argument("--processes", type=int, default=4, help="processes the fleet's sessions are spread over")
    parser.add_argument("--period", type=float, default=1.0, help="seconds between an actor's requests")
    parser.add_argument("--seconds", type=float, default=30.0, help="measuring time per fleet size")
    parser.add_argument("overrides", nargs="*", help="key=value overrides of the run config")
    args = parser.parse_args(argv)
    return run(args.config, args.overrides, args.actors, args.processes, args.period, args.seconds)


if __name__ == "__main__":
    raise SystemExit(main())
