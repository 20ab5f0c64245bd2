"""Counting and logging refused messages without letting a flood of them drown the log.

A misconfigured actor can send thousands of bad frames a second; each is refused (see `codec.Rejected`), counted
by reason, and reported at most once per reason every `log_every_s` seconds, with the number of reports held back
since the last line. The counts feed the metrics, so a refused message is never silent.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from impulse.bus.codec import REASONS

LOGGER = logging.getLogger("impulse.bus")


@dataclass
class _ReasonLog:
    last_logged: float
    suppressed: int = 0


class RejectCounter:
    """Thread-safe counts of refused messages by reason, with rate-limited warnings.

    `clock` is injectable so that tests can step time instead of sleeping.
    """

    def __init__(
        self,
        log_every_s: float = 10.0,
        *,
        logger: logging.Logger = LOGGER,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if log_every_s < 0:
            raise ValueError(f"log_every_s must be >= 0, got {log_every_s}")
        self.log_every_s = log_every_s
        self._logger = logger
        self._clock = clock
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._logs: dict[str, _ReasonLog] = {}

    def record(self, reason: str, source: str, detail: str) -> None:
        """Count one refused message from `source` (a key or sender id) and warn unless this reason warned lately."""
        if reason not in REASONS:
            raise ValueError(f"unknown reject reason {reason!r}; expected one of {REASONS}")
        now = self._clock()
        with self._lock:
            self._counts[reason] = self._counts.get(reason, 0) + 1
            log = self._logs.get(reason)
            if log is not None and now - log.last_logged < self.log_every_s:
                log.suppressed += 1
                return
            suppressed = log.suppressed if log is not None else 0
            self._logs[reason] = _ReasonLog(last_logged=now)
        self._logger.warning(
            "refused a message: reason=%s source=%s detail=%s (%d more with this reason since the last report)",
            reason,
            source,
            detail,
            suppressed,
        )

    def counts(self) -> dict[str, int]:
        """Refused messages so far, by reason (only reasons seen at least once)."""
        with self._lock:
            return dict(self._counts)

    @property
    def total(self) -> int:
        """Refused messages so far, all reasons together."""
        with self._lock:
            return sum(self._counts.values())
