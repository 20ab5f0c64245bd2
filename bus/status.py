"""Status lines: what every process tells the launcher's display (and anyone else watching the run).

A status is a small JSON object (steps/s, policy version, queue depth, drop and reject counts, ...) sent as the
meta of a METRICS frame on `metrics/<role>/<id>` at most every `every_s` seconds. It is published with the DROP
congestion policy at background priority: a slow or absent watcher never holds a training process back.
"""

from __future__ import annotations

import time
from typing import Any

import zenoh

from bus.codec import Kind, Rejected, decode, encode
from bus.inbox import Received
from bus.session import Bus


class StatusPublisher:
    """Rate-limited status messages of one process."""

    def __init__(self, bus: Bus, every_s: float) -> None:
        self._bus = bus
        self._every_s = every_s
        self._publisher = bus.publisher(
            bus.keys.metrics(bus.role, bus.ident), block=False, priority=zenoh.Priority.BACKGROUND
        )
        self._last = -float("inf")
        self._seq = 0

    def due(self) -> bool:
        """Whether the next status should be sent now."""
        return time.monotonic() - self._last >= self._every_s

    def publish(self, status: dict[str, Any]) -> None:
        """Send `status` (JSON-serialisable values) now."""
        self._last = time.monotonic()
        self._seq += 1
        frame = encode(Kind.METRICS, {}, run=self._bus.keys.run, seq=self._seq,
                       sender=f"{self._bus.role}/{self._bus.ident}", meta=status)
        self._publisher.put(frame)


def read_status(received: Received, run: str) -> tuple[str, dict[str, Any]]:
    """(sender "role/id", status) of a status message; raises `Rejected` for anything else."""
    message = decode(received.payload, run=run, kinds=Kind.METRICS)
    if not message.sender or not isinstance(message.meta, dict):
        raise Rejected("schema", "a status message without sender or status")
    return message.sender, message.meta
