"""The live status display of `impulse launch`: one line per process, from the status messages they publish.

On a terminal the block is redrawn in place once a second; otherwise (a log file, CI) it is written as log lines
every `log_every_s` seconds, so a long run's log stays readable. A process that has exited shows how (exit status
or signal), what happens next (a restart, or that the launcher gave up on it) and the error line it ended with,
the line cut to the terminal's width.

A restarted process shows "starting" until its own first status arrives, never the last status of the incarnation
before it, which stays the newest heard under its name until then (`current_status`).
"""

from __future__ import annotations

import logging
import shutil
import sys
import time
from typing import Any, TextIO

from impulse.deploy.runtime.supervisor import EXIT_CANNOT_RUN, Child, describe_exit

log = logging.getLogger("impulse.launch")


def _number(value: Any, fmt: str = "{:,.0f}") -> str:
    return "-" if value is None else fmt.format(value)


def _total(counts: Any) -> int:
    """All refusals of a status's `rejected` counts by reason."""
    return sum(v for v in counts.values() if isinstance(v, int)) if isinstance(counts, dict) else 0


STARTING = "starting (importing JAX, compiling; cached after the first run)"


def starting_part(elapsed_s: float) -> str:
    """The line of a process that has published no status yet, with how long it has been starting (a compile of
    a large batch takes minutes on a CPU: the count shows it is not stuck)."""
    return f"starting for {elapsed_s:.0f} s (importing JAX, compiling; cached after the first run)"
COLUMNS_WITHOUT_TERMINAL = 200
"""The width lines of exited processes are cut to when the output is not a terminal (a log file)."""


STALE_SHOWN_AFTER = 20
"""A learner whose last this many batches were all stale says so on its line (it warns and republishes then)."""


def alarms_part(status: dict[str, Any]) -> str:
    """What needs a person's eye, early in a line so that a narrow terminal still shows it ("" when all is well):
    updates skipped as non-finite, a learner whose batches are all stale, several learner instances seen by a
    follower, a follower that had to re-sync."""
    alarms = []
    if _count_of(status, "skipped_non_finite"):
        alarms.append(f"SKIPPED {status['skipped_non_finite']} non-finite updates")
    if _count_of(status, "stale_streak") >= STALE_SHOWN_AFTER:
        alarms.append(f"last {status['stale_streak']} batches ALL STALE")
    if _count_of(status, "learners_seen") > 1:
        alarms.append(f"{status['learners_seen']} LEARNERS on the bus")
    if _count_of(status, "resyncs"):
        alarms.append(f"re-synced {status['resyncs']}x")
    return "".join(f" | {alarm}" for alarm in alarms)


def _count_of(status: dict[str, Any], key: str) -> int:
    value = status.get(key)
    return value if isinstance(value, int) and not isinstance(value, bool) else 0


def learner_line(status: dict[str, Any] | None) -> str:
    if status is None:
        return STARTING
    drops = " ".join(f"{label} {status.get(key, 0)}" for label, key in (
        ("stale", "dropped_stale"), ("old-epoch", "dropped_old_epoch"), ("overflow", "dropped_overflow"),
        ("inbox-full", "dropped_inbox_full"), ("lost", "lost")))
    rejected = _total(status.get("rejected"))
    return (f"v{status['policy_version']} epoch {status['epoch']}{alarms_part(status)} | update {status['update']:,}/"
            f"{status['num_updates']:,} | {_number(status.get('updates_per_s'), '{:.2f}')} upd/s | "
            f"{_number(status.get('consumed_steps_per_s'))} steps/s consumed | queue {status.get('queue', 0)} | "
            f"dropped {drops} | rejected {rejected} | solved {_number(status.get('solve_rate'), '{:.0%}')}"
            f"{_evaluation_part(status.get('evaluation'))}")


def _evaluation_part(evaluation: Any) -> str:
    """The learner's newest evaluation, for its line ("" before the first)."""
    if not isinstance(evaluation, dict) or "policy_version" not in evaluation:
        return ""
    return f" | eval v{evaluation['policy_version']} {_number(evaluation.get('mean'), '{:.0%}')}"


def actor_line(status: dict[str, Any] | None, lag: int | None) -> str:
    if status is None:
        return STARTING
    waiting = f" | waiting for {status['waiting']}" if status.get("waiting") else ""
    return (f"{_number(status.get('steps_per_s'))} steps/s | v{status['policy_version']}{alarms_part(status)} | lag "
            f"{'-' if lag is None else lag} | in flight {status.get('in_flight', 0)} | dropped "
            f"{status.get('dropped_no_credit', 0)} written off {status.get('written_off', 0)} | rejected "
            f"{_total(status.get('rejected'))} | levels {status.get('levels', '?')}{waiting}"
            f"{streaming_part(status.get('monitor'))}")


def evaluator_line(status: dict[str, Any] | None) -> str:
    """The evaluator's line: the newest policy it holds, the last one it scored and how, what it skipped."""
    if status is None:
        return STARTING
    if status.get("scored_version") is None:
        held = status.get("policy_version", -1)
        return "waiting for the learner's weights" if held < 0 else f"v{held} | scoring its first policy"
    groups = " ".join(f"{name} {rate:.0%}" for name, rate in sorted(status.get("groups", {}).items()))
    return (f"v{status['policy_version']}{alarms_part(status)} | scored v{status['scored_version']}: mean "
            f"{_number(status.get('mean'), '{:.0%}')}{' ' + groups if groups else ''} in "
            f"{_number(status.get('seconds'), '{:.1f}')} s | {status.get('evaluations', 0)} evaluations, "
            f"{status.get('skipped', 0)} points skipped | rejected {_total(status.get('rejected'))}")


def recorder_line(status: dict[str, Any] | None) -> str:
    """The recorder's line: what it has written, what waits for the next shard, what it had to leave out."""
    if status is None:
        return STARTING
    full = " | FULL: recording stopped" if status.get("full") else ""
    return (f"{status.get('episodes_written', 0):,} episodes ({status.get('steps_written', 0):,} steps) in "
            f"{status.get('shards_written', 0)} shards, {status.get('bytes_used', 0) / 1e6:.1f} MB | waiting "
            f"{status.get('pending_steps', 0):,} steps | cut {status.get('episodes_cut', 0)} | rejected "
            f"{_total(status.get('rejected'))}{full}")


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
    rejected = _total(status.get("rejected"))
    return (f"{status.get('method', '?')} | buffer {_number(status.get('buffer_fill'), '{:.0%}')} full, score "
            f"{_number(status.get('score_mean'), '{:.3f}')}, learnable {_number(status.get('learnable'), '{:.0%}')} | "
            f"staged {status.get('staged', 0)} | served {status.get('samples', 0):,} | results "
            f"{status.get('results', 0):,} | dropped {status.get('dropped_inbox_full', 0)} | rejected {rejected}"
            f"{_refill_part(status)}")


def _refill_part(status: dict[str, Any]) -> str:
    """Batch-scored SFL's refills, for the curriculum's line ("" for the other curricula)."""
    if "refills" not in status:
        return ""
    last = status.get("last_refill") or {}
    newest = f" (v{last['version']}, {last.get('seconds', 0):.0f} s)" if "version" in last else ""
    filling = ", holding level requests" if status.get("filling") else ""
    return f" | refills {status['refills']}{newest}{', scoring' if status.get('scoring') else ''}{filling}"


INCARNATION_FIELDS = ("pid", "incarnation", "epoch")
"""Status fields that differ from one incarnation of a process to the next (an actor's and the curriculum's random
incarnation, the learner's epoch; `pid` where a status carries it)."""


def current_status(child: Child, status: dict[str, Any] | None) -> dict[str, Any] | None:
    """`status`, the newest heard under `child`'s name, if it is from the incarnation running now; None if it is
    from an earlier one (a process restarted after kill -9 sends nothing for a while). An earlier incarnation's
    status is one that says so (its `pid` is not the child's, its `sent_at` is before this start), one the display
    showed for the earlier incarnation (`Child.shown_status`), or one that arrived after that but carries the same
    `INCARNATION_FIELDS`. Records what it shows in `child.shown_status`."""
    if status is None:
        return None
    if isinstance(status.get("pid"), int) and status["pid"] != child.pid:
        return None
    sent_at = status.get("sent_at")
    if isinstance(sent_at, int | float) and sent_at < child.started_wall:
        return None
    shown = child.shown_status
    if shown is not None and shown[0] != child.started_at:  # what the display last showed was an earlier one's
        earlier = shown[1]
        if status is earlier or _same_incarnation(status, earlier):
            return None
    child.shown_status = (child.started_at, status)
    return status


def _same_incarnation(status: dict[str, Any], other: Any) -> bool:
    """Whether two statuses carry the same incarnation fields (and carry any)."""
    if not isinstance(other, dict):
        return False
    known = [key for key in INCARNATION_FIELDS if key in status and key in other]
    return bool(known) and all(status[key] == other[key] for key in known)


def render(statuses: dict[str, dict[str, Any]], children: list[Child], learner_name: str,
           curriculum_name: str = "curriculum", viewer_name: str = "viewer", evaluator_name: str = "evaluator",
           recorder_name: str = "recorder", columns: int | None = None) -> list[str]:
    """The display's lines: every child with its process state, then its latest status (the line of a child that
    has exited ends with its error line), each cut to `columns` (default: the terminal's width) so that a redraw
    never wraps."""
    if columns is None:
        columns = shutil.get_terminal_size((COLUMNS_WITHOUT_TERMINAL, 24)).columns
    learner = statuses.get(learner_name)
    lags = learner.get("actor_lag", {}) if isinstance(learner, dict) else {}
    width = max(len(c.name) for c in children)
    lines = []
    for child in children:
        if child.pid is None:
            lines.append(_cut(f"{child.name:<{width}}  {exited_state(child)}", columns))
            continue
        status = current_status(child, statuses.get(child.name))
        try:
            if status is None and child.name != viewer_name:  # nothing heard yet: say how long it has been
                body = starting_part(time.monotonic() - child.started_at)
            elif child.name == learner_name:
                body = learner_line(status)
            elif child.name == curriculum_name:
                body = curriculum_line(status)
            elif child.name == viewer_name:
                body = f"Rerun viewer (its address is logged above and in {child.log_path})"
            elif child.name == evaluator_name:
                body = evaluator_line(status)
            elif child.name == recorder_name:
                body = recorder_line(status)
            else:
                body = actor_line(status, lags.get(child.name) if isinstance(lags, dict) else None)
        except (TypeError, ValueError, KeyError, AttributeError):  # a status frame with fields of the wrong types
            body = "malformed status"
        lines.append(_cut(f"{child.name:<{width}}  pid {child.pid} restarts {child.restarts} | {body}", columns))
    return lines


def exited_state(child: Child) -> str:
    """A child that is not running: how it ended, what happens next, then its error line."""
    if child.last_exit is None:
        return f"stopped (restarts {child.restarts})"
    state = describe_exit(child.last_exit)
    if child.gave_up and child.last_exit == EXIT_CANNOT_RUN:
        state += "; cannot run with this configuration"
    elif child.gave_up:
        state += f"; gave up after {child.streak} identical failures"
    elif child.restart_at is not None:
        state += f"; restarting in {max(child.restart_at - time.monotonic(), 0):.0f} s"
    state += f" (restarts {child.restarts})"
    return f"{state} | {child.error_line}" if child.error_line else state


def _cut(line: str, columns: int) -> str:
    """`line` no wider than `columns` ("..." marks a cut), so a redrawn block never wraps."""
    return line if len(line) <= columns else line[:max(columns - 3, 0)] + "..."


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
