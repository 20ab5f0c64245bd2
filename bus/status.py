"""Status lines: what every process tells the launcher's display (and anyone else watching the run).

A status is a small JSON object (steps/s, policy version, queue depth, drop and reject counts, ...) sent as the
meta of a METRICS frame on `<role>/status/<id>` at most every `every_s` seconds. It is published with the DROP
congestion policy at background priority: a slow or absent watcher never holds a training process back.

Who sent a status is read from its key, which only that role may publish under where a router enforces access
control (`bus.keys`); the `name` a status carries is for display only.
"""

from __future__ import annotations

import os
import time
from collections import Counter
from typing import Any, NamedTuple

import zenoh

from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.inbox import Received
from impulse.bus.keys import Keys
from impulse.bus.session import Bus


class StatusPublisher:
    """Rate-limited status messages of one process."""

    def __init__(self, bus: Bus, every_s: float) -> None:
        self._bus = bus
        self._every_s = every_s
        self._publisher = bus.publisher(
            bus.keys.status(bus.role, bus.ident), block=False, priority=zenoh.Priority.BACKGROUND
        )
        self._last = -float("inf")

    def due(self) -> bool:
        """Whether the next status should be sent now."""
        return time.monotonic() - self._last >= self._every_s

    def publish(self, status: dict[str, Any]) -> None:
        """Send `status` (JSON-serialisable values) now."""
        self._last = time.monotonic()
        stamp = self._bus.stamp
        # Which process sent it, and when: a display tells a restarted process's first line from its predecessor's.
        status = {**status, "pid": os.getpid(), "sent_at": time.time()}
        frame = encode(Kind.METRICS, {}, run=stamp.run, seq=stamp.next_seq(Kind.METRICS), meta=status)
        self._publisher.put(frame)


class Status(NamedTuple):
    """A status message as received: who sent it (from its key) and what it says."""

    role: str
    ident: str
    status: dict[str, Any]


def read_status(received: Received, keys: Keys) -> Status:
    """The status a message on a status key of `keys`' run carries; raises `Rejected` for anything else."""
    try:
        role, ident = keys.parse_status(received.key)
    except ValueError as err:
        raise Rejected("schema", str(err)) from None
    message = decode(received.payload, run=keys.run, kinds=Kind.METRICS)
    if not message.meta:
        raise Rejected("schema", "a status message without a status")
    return Status(role, ident, message.meta)


MAX_TRACKED_PROCESSES = 4096
"""Process incarnations whose counters `DropTotals` keeps apart; older ones are folded into one sum."""
_MAX_COUNT = 1 << 62


def _count(value: Any) -> int | None:
    """A counter's value if it is a plausible count (a non-negative int, not a bool), else None."""
    return value if type(value) is int and 0 <= value < _MAX_COUNT else None


class DropTotals:
    """What other processes dropped and refused, summed over every incarnation of each whose status was heard.

    A process's counters restart at zero when it restarts, so the newest status of each incarnation (the
    `incarnation` a status carries, drawn by the process at start, or else the `pid` every `StatusPublisher`
    adds: the recorder and the evaluator draw no incarnation) is kept and all of them are summed: the
    learner writes these sums to metrics.jsonl, so a drop anywhere in the run is counted there. Counted fields:
    integer fields named `dropped_*`, `written_off` and `lost`, and the `rejected` counts by reason. Values that
    are not plausible counts are ignored; `state()`/`restore()` carry them across a restart of the learner.
    """

    def __init__(self) -> None:
        self._latest: dict[str, dict[str, int]] = {}
        self._retired: Counter[str] = Counter()

    @staticmethod
    def counters(role: str, status: dict[str, Any]) -> dict[str, int]:
        """The drop counters of one status, named `<role>/<field>` and `<role>/rejected/<reason>`."""
        found: dict[str, int] = {}
        for field, value in status.items():
            if isinstance(field, str) and (field.startswith("dropped_") or field in ("written_off", "lost")):
                count = _count(value)
                if count is not None:
                    found[f"{role}/{field}"] = count
        rejected = status.get("rejected")
        if isinstance(rejected, dict):
            for reason, value in rejected.items():
                count = _count(value)
                if isinstance(reason, str) and count is not None:
                    found[f"{role}/rejected/{reason}"] = count
        return found

    def note(self, heard: Status) -> None:
        """Keep the counters of this status as its incarnation's newest."""
        name = f"{heard.role}/{heard.ident}#{incarnation_of(heard.status)}"
        if name not in self._latest and len(self._latest) >= MAX_TRACKED_PROCESSES:
            oldest = next(iter(self._latest))
            self._retired.update(self._latest.pop(oldest))
        self._latest[name] = self.counters(heard.role, heard.status)

    def totals(self) -> dict[str, int]:
        """Every counter summed over all incarnations heard (and restored)."""
        total = Counter(self._retired)
        for counts in self._latest.values():
            total.update(counts)
        return dict(sorted(total.items()))

    def state(self) -> dict[str, Any]:
        """What `restore` needs to go on counting (plain JSON), to be stored with a checkpoint."""
        return {"by_process": {name: dict(counts) for name, counts in self._latest.items()},
                "retired": dict(self._retired)}

    def restore(self, state: object) -> None:
        """Go on from a `state()` (anything else is ignored): a process still running keeps its entry, so its next
        status replaces its counters instead of adding to them."""
        if not isinstance(state, dict):
            return
        by_process, retired = state.get("by_process"), state.get("retired")
        if isinstance(by_process, dict):
            self._latest = {name: plausible_counts(counts) for name, counts in by_process.items()
                            if isinstance(name, str)}
        self._retired = Counter(plausible_counts(retired))


def incarnation_of(status: dict[str, Any]) -> str:
    """What tells one incarnation of a process from the next in its status: its drawn `incarnation` if it sends
    one, else its `pid` (empty if it sends neither, or nothing plausible)."""
    for field, mark in (("incarnation", ""), ("pid", "pid:")):
        value = _count(status.get(field))
        if value is not None:
            return f"{mark}{value}"
    return ""


def plausible_counts(value: object) -> dict[str, int]:
    """The plausible counts of a mapping: its str keys with non-negative int values (empty for anything else).
    For counters read back from a checkpoint or heard from another process."""
    if not isinstance(value, dict):
        return {}
    return {k: v for k, v in value.items() if isinstance(k, str) and _count(v) is not None}
