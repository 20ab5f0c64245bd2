"""Asking a running curriculum service from outside the run: its live knobs (`curriculum/knobs`), its buffer
(`curriculum/inspect`) and a level sent in (`curriculum/inject`), the three requests `curriculum.service` answers.

`impulse curriculum set|get|inspect|inject` and the studio's console both ask through `CurriculumClient`, as
the operator role (the only role a router lets ask them). Every failure to get a readable answer (no service
on the bus, no reply in time, a malformed reply) is one `CurriculumUnreachable` with a sentence for the user;
a service's refusal is not a failure: it is the reply (`{"ok": false, "error": ...}`, or a report's `error`).
"""

from __future__ import annotations

from typing import Any

from impulse.bus.codec import Rejected
from impulse.bus.config import BusConfig
from impulse.bus.control import Report, control_reply, control_request, decode_report
from impulse.bus.keys import OPERATOR
from impulse.bus.session import Bus

ANSWER_TIMEOUT_S = 30.0


class CurriculumUnreachable(Exception):
    """No readable answer from the run's curriculum service; the message says what was tried."""


class CurriculumClient:
    """An operator session on run `run`'s bus, named `caller` (e.g. "cli-1234"), for the curriculum service's
    requests. Use it as a context manager; each request waits first until the service's queryable is known to
    this new session, since a query sent before that finds nobody and returns at once."""

    def __init__(self, bus: BusConfig, run: str, caller: str, timeout_s: float = ANSWER_TIMEOUT_S):
        self.bus_config, self.run, self.timeout_s = bus, run, timeout_s
        self._session = Bus(bus, run, OPERATOR, caller)

    def __enter__(self) -> CurriculumClient:
        self._session.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._session.__exit__(*exc)

    def knobs(self, assignments: list[str] | None = None) -> dict[str, Any]:
        """The live knobs (`{"ok", "method", "knobs"}`), after applying `assignments` ("replay_prob=0.8", ...)
        when given (the reply then also lists what `changed`, or says why it refused all of them)."""
        request: dict[str, Any] = {} if assignments is None else {"set": list(assignments)}
        return self._control(self._session.keys.curriculum_knobs, request)

    def inspect(self, top: int, levels: bool = False) -> Report:
        """The buffer's report (summary, histograms, the `top` levels by score), with those levels' arrays when
        `levels` is set."""
        payload = self._ask(self._session.keys.curriculum_inspect, control_request(top=top, levels=levels))
        try:
            return decode_report(payload, self.run)
        except Rejected as err:
            raise CurriculumUnreachable(f"unreadable answer from the curriculum service: {err}") from err

    def inject(self, document: dict[str, Any]) -> dict[str, Any]:
        """Send a Kinetix level-file object into the buffer: `{"ok": true, "slot", "level_id", "evicted"}` or the
        service's reason for refusing it."""
        return self._control(self._session.keys.curriculum_inject, {"level": document})

    def _control(self, key: str, request: dict[str, Any]) -> dict[str, Any]:
        payload = self._ask(key, control_request(**request))
        try:
            return control_reply(payload)
        except ValueError as err:
            raise CurriculumUnreachable(f"unreadable answer from the curriculum service: {err}") from err

    def _ask(self, key: str, payload: bytes) -> bytes:
        if self._session.wait_queryable(key, self.timeout_s):
            replies = self._session.get(key, payload=payload, timeout_s=self.timeout_s)
            if replies:
                return replies[0]
        hub = self.bus_config.connect or self.bus_config.hub
        raise CurriculumUnreachable(f"no curriculum service answered on {key} within {self.timeout_s:.0f} s (is run "
                                    f"{self.run!r} running with env.levels=random, on hub {hub}?)")
