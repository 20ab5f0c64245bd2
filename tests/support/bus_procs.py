"""Bus processes for the session tests, run as `python tests/support/bus_procs.py <role> [args]`, and the test-side
handle that starts them and reads what they report.

Each process prints one JSON object per line on stdout ({"event": ...}), stops when a line "stop" arrives on
stdin (or stdin closes), closes its Bus, prints {"event": "closed"} and exits by itself; the tests assert that it
does so within a few seconds, which catches zenoh's exit hang. Roles:

- hub ENDPOINT: `run_hub` until stopped; reports "ready" once listening.
- peer ENDPOINT RUN IDENT OTHER[,OTHER...]: sends CONTROL frames to each other peer (on `peer/<from>/<to>`) every 50 ms,
  saying whether it has heard from that peer; reports {"event": "linked", "other": ...} once it has heard from a
  peer that has also heard from it, i.e. messages went both ways.
- alive ENDPOINT RUN IDENT: only holds its liveliness token.
- latest ENDPOINT RUN: publishes weights versions 1, 2, 3 on weights/policy through the latest publisher.
- levels ENDPOINT RUN: serves levels/sample, answering "n=K" with a LEVELS frame holding ids 0..K-1.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.config import BusConfig
from impulse.bus.keys import OPERATOR
from impulse.bus.session import Bus, run_hub
from tests.support.paths import REPO

REPO_ROOT = REPO
PEER_ROLE = OPERATOR
SEND_EVERY_S = 0.05


def report(event: str, **fields: Any) -> None:
    print(json.dumps({"event": event, **fields}), flush=True)


def stop_flag() -> threading.Event:
    """Set when stdin says "stop" or closes (the test process died): a process never outlives its test."""
    stop = threading.Event()

    def watch() -> None:
        for line in sys.stdin:
            if line.strip() == "stop":
                break
        stop.set()

    threading.Thread(target=watch, daemon=True).start()
    return stop


def announce_ready(stop: threading.Event) -> Callable[[], bool]:
    """A stop callable for `run_hub` that reports "ready" on its first call, i.e. once the hub is listening."""
    announced = threading.Event()

    def stopped() -> bool:
        if not announced.is_set():
            announced.set()
            report("ready")
        return stop.is_set()

    return stopped


def run_peer(config: BusConfig, run: str, ident: str, others: list[str], stop: threading.Event) -> None:
    with Bus(config, run, PEER_ROLE, ident) as bus:
        inbox = bus.inbox(bus.keys.own(PEER_ROLE, "peer", "*", ident), 64)
        publishers = {other: bus.publisher(bus.keys.own(PEER_ROLE, "peer", ident, other)) for other in others}
        heard: set[str] = set()
        linked: set[str] = set()
        report("ready", ident=ident)
        seq = 0
        while not stop.is_set():
            for other, publisher in publishers.items():
                meta = {"heard_you": other in heard}
                publisher.put(encode(Kind.CONTROL, {}, run=run, seq=seq, meta=meta))
            seq += 1
            deadline = time.monotonic() + SEND_EVERY_S
            while (received := inbox.wait(max(0.0, deadline - time.monotonic()))) is not None:
                try:
                    message = decode(received.payload, run=run, kinds=Kind.CONTROL)
                except Rejected as exc:
                    bus.rejects.record(exc.reason, received.key, exc.detail)
                    continue
                sender = received.key.split("/")[-2]  # peer/<from>/<to>
                heard.add(sender)
                if message.meta.get("heard_you") and sender not in linked:
                    linked.add(sender)
                    report("linked", ident=ident, other=sender)
    report("closed")


def run_alive(config: BusConfig, run: str, ident: str, stop: threading.Event) -> None:
    with Bus(config, run, "actor", ident):
        report("ready", ident=ident)
        stop.wait()
    report("closed")


def run_latest(config: BusConfig, run: str, stop: threading.Event) -> None:
    with Bus(config, run, "learner", "0") as bus:
        publisher = bus.latest_publisher(bus.keys.weights_policy)
        for version in (1, 2, 3):
            weights = {"w": np.full((4, 3), version, np.float32)}
            publisher.put(encode(Kind.WEIGHTS, weights, run=run, policy_version=version))
        report("published", version=3)
        stop.wait()
    report("closed")


def run_levels(config: BusConfig, run: str, stop: threading.Event) -> None:
    with Bus(config, run, "curriculum", "0") as bus:
        queries = bus.queryable(bus.keys.levels_sample, 8)
        report("ready")
        while not stop.is_set():
            query = queries.wait(0.05)
            if query is None:
                continue
            count = int(query.parameters.get("n", "0"))
            ids = np.arange(count, dtype=np.int64)
            meta = {"asked_by": query.parameters.get("actor", ""), "note": (query.payload or b"").decode()}
            query.reply(encode(Kind.LEVELS, {"level_id": ids}, run=run, meta=meta))
    report("closed")


def main(argv: list[str]) -> None:
    role, endpoint, *rest = argv
    config = BusConfig(hub=endpoint)
    stop = stop_flag()
    if role == "hub":
        run_hub(config, announce_ready(stop))
        report("closed")
    elif role == "peer":
        run, ident, others = rest
        run_peer(config, run, ident, others.split(","), stop)
    elif role == "alive":
        run, ident = rest
        run_alive(config, run, ident, stop)
    elif role == "latest":
        (run,) = rest
        run_latest(config, run, stop)
    elif role == "levels":
        (run,) = rest
        run_levels(config, run, stop)
    else:
        raise SystemExit(f"unknown role {role!r}")


class BusProcess:
    """A running bus_procs.py process: its JSON events arrive on a queue read by a background thread."""

    def __init__(self, *args: str) -> None:
        self.args = args
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
        self.proc = subprocess.Popen(
            [sys.executable, "-u", __file__, *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO_ROOT,
            env=env,
        )
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self.output: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line.rstrip())
            try:
                event = json.loads(line)
            except ValueError:
                continue  # zenoh's own log lines
            if isinstance(event, dict):
                self.events.put(event)

    def expect(self, event: str, timeout_s: float = 10.0, **fields: Any) -> dict[str, Any]:
        """The next event named `event` with these field values (skipping others); fails after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                got = self.events.get(timeout=max(left, 0.0))
            except queue.Empty:
                raise AssertionError(
                    f"{self.args}: no {event} {fields} within {timeout_s} s; output:\n" + "\n".join(self.output)
                ) from None
            if got.get("event") == event and all(got.get(k) == v for k, v in fields.items()):
                return got

    def stop(self, timeout_s: float = 5.0) -> int:
        """Ask the process to stop; assert it exits by itself within `timeout_s` (else kill it and fail)."""
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            try:
                self.proc.stdin.write("stop\n")
                self.proc.stdin.flush()
            except BrokenPipeError:
                pass
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError(f"{self.args} did not exit within {timeout_s} s of being told to stop") from None

    def kill(self) -> None:
        """SIGKILL, as a crash would."""
        self.proc.kill()
        self.proc.wait()

    def cleanup(self) -> None:
        """Kill the process if a failed test left it running."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdin is not None:
            self.proc.stdin.close()


if __name__ == "__main__":
    main(sys.argv[1:])
