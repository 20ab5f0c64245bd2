"""The live status display of `impulse launch`: one line per process, from the status messages they publish.

On a terminal the block is redrawn in place once a second; otherwise (a log file, CI) it is written as log lines
every `log_every_s` seconds, so a long run's log stays readable.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any, TextIO

from deploy.supervisor import Child, describe_exit

log = logging.getLogger("impulse.launch")


def _number(value: Any, fmt: str = "{:,.0f}") -> str:
    return "-" if value is None else fmt.format(value)


STARTING = "starting (importing JAX, compiling; cached after the first run)"


def learner_line(status: dict[str, Any] | None) -> str:
    if status is None:
        return STARTING
    drops = " ".join(f"{label} {status.get(key, 0)}" for label, key in (
        ("stale", "dropped_stale"), ("old-epoch", "dropped_old_epoch"), ("overflow", "dropped_overflow"),
        ("lost", "lost")))
    rejected = sum(status.get("rejected", {}).values())
    return (f"v{status['policy_version']} epoch {status['epoch']} | update {status['update']:,}/"
            f"{status['num_updates']:,} | {_number(status.get('updates_per_s'), '{:.2f}')} upd/s | "
            f"{_number(status.get('consumed_steps_per_s'))} steps/s consumed | queue {status.get('queue', 0)} | "
            f"dropped {drops} | rejected {rejected} | solved {_number(status.get('solve_rate'), '{:.0%}')}")


def actor_line(status: dict[str, Any] | None, lag: int | None) -> str:
    if status is None:
        return STARTING
    waiting = f" | waiting for {status['waiting']}" if status.get("waiting") else ""
    return (f"{_number(status.get('steps_per_s'))} steps/s | v{status['policy_version']} | lag "
            f"{'-' if lag is None else lag} | in flight {status.get('in_flight', 0)} | dropped "
            f"{status.get('dropped_no_credit', 0)} | levels {status.get('levels', '?')}{waiting}"
            f"{streaming_part(status.get('monitor'))}")


def streaming_part(monitor: dict[str, Any] | None) -> str:
    """What an actor streams to Rerun, for its status line ("" when monitoring is off)."""
    if not monitor:
        return ""
    if not monitor.get("viewer"):
        return " | stream: no viewer"
    return (f" | stream: {monitor.get('frames_logged', 0):,} frames, {monitor.get('rollouts_dropped', 0)} rollouts "
            "dropped")


def curriculum_line(status: dict[str, Any] | None) -> str:
    if status is None:
        return STARTING
    rejected = sum(status.get("rejected", {}).values())
    return (f"{status.get('method', '?')} | buffer {_number(status.get('buffer_fill'), '{:.0%}')} full, score "
            f"{_number(status.get('score_mean'), '{:.3f}')}, learnable {_number(status.get('learnable'), '{:.0%}')} | "
            f"staged {status.get('staged', 0)} | served {status.get('samples', 0):,} | results "
            f"{status.get('results', 0):,} | rejected {rejected}")


def render(statuses: dict[str, dict[str, Any]], children: list[Child], learner_name: str,
           curriculum_name: str = "curriculum", viewer_name: str = "viewer") -> list[str]:
    """The display's lines: every child with its process state, then its latest status."""
    learner = statuses.get(learner_name)
    lags = learner.get("actor_lag", {}) if isinstance(learner, dict) else {}
    width = max(len(c.name) for c in children)
    lines = []
    for child in children:
        if child.pid is None:
            if child.restart_at is not None:
                state = (f"{describe_exit(child.last_exit or 0)}; restarting in "
                         f"{max(child.restart_at - time.monotonic(), 0):.0f} s")
            else:
                state = "stopped" if child.last_exit is None else describe_exit(child.last_exit)
            lines.append(f"{child.name:<{width}}  {state} (restarts {child.restarts})")
            continue
        status = statuses.get(child.name)
        try:
            if child.name == learner_name:
                body = learner_line(status)
            elif child.name == curriculum_name:
                body = curriculum_line(status)
            elif child.name == viewer_name:
                body = f"Rerun viewer (its address is logged above and in {child.log_path})"
            else:
                body = actor_line(status, lags.get(child.name) if isinstance(lags, dict) else None)
        except (TypeError, ValueError, KeyError, AttributeError):  # a status frame with fields of the wrong types
            body = "malformed status"
        lines.append(f"{child.name:<{width}}  pid {child.pid} restarts {child.restarts} | {body}")
    return lines


class StatusDisplay:
    def __init__(self, stream: TextIO | None = None, redraw_every_s: float = 1.0, log_every_s: float = 10.0):
        self.stream = stream or sys.stdout
        self.interactive = self.stream.isatty()
        self.every_s = redraw_every_s if self.interactive else log_every_s
        self._last = -float("inf")
        self._drawn = 0

    def due(self) -> bool:
        return time.monotonic() - self._last >= self.every_s

    def show(self, lines: list[str]) -> None:
        self._last = time.monotonic()
        if not self.interactive:
            log.info("status\n  %s", "\n  ".join(lines))
            return
        if self._drawn:
            self.stream.write(f"\x1b[{self._drawn}F")
        for line in lines:
            self.stream.write(line + "\x1b[K\n")
        self.stream.flush()
        self._drawn = len(lines)

    def forget(self) -> None:
        """Start the next block below whatever was printed since (a log line), instead of over it."""
        self._drawn = 0
