"""The live status display of `impulse launch`: one row per process, from the status messages they publish.

Each process's status is read into fields (`Part`), once, by its role's function (`learner_parts`,
`actor_parts`, ...); the fields make both ways the display is shown:

- on a terminal, a table at the bottom of the screen, redrawn in place once a second with the log lines scrolling
  above it (`StatusDisplay`, on rich's Live display): one row per process with the fields that matter first
  (process, phase, alarms, progress, solve rate, lag, drops as one total, restarts), then the drops by kind and
  the rest, the columns left out by priority so that the table fits the terminal's width (at 80 columns:
  process, phase, alarms, progress, solve rate and drops);
- otherwise (a log file, CI), a plain line per process, logged every `log_every_s` seconds (`render`), as it was
  before the table, so that a long run's log stays readable and what scripts look for in it stays there.

A process that has exited shows how (exit status or signal) and what happens next (a restart, or that the
launcher gave up on it) in its phase, and its error line below the table. A process that publishes its phase
(the learner: compiling, training, checkpointing, evaluating its final policy) shows it with its seconds so far.

A restarted process shows "starting" until its own first status arrives, never the last status of the incarnation
before it, which stays the newest heard under its name until then (`current_status`).
"""

from __future__ import annotations

import logging
import shutil
import sys
import time
from collections.abc import Callable, Collection, Mapping
from typing import Any, NamedTuple, TextIO

from rich.console import Console, ConsoleOptions, Group, RenderableType, RenderResult
from rich.text import Text

from impulse.deploy.runtime.exit_codes import EXIT_CANNOT_RUN
from impulse.deploy.runtime.progress import Column, LiveArea, fitted_table, interactive
from impulse.deploy.runtime.supervisor import Child, describe_exit

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

# The table's columns, by key.
PROCESS, PHASE, ALARMS, PROGRESS, SOLVED, LAG, DROPS, RESTARTS, BREAKDOWN, DETAILS = (
    "process", "phase", "alarms", "progress", "solved", "lag", "drops", "restarts", "breakdown", "details")

TABLE_COLUMNS = (
    Column(PROCESS, "process", 0, required=True),
    Column(PHASE, "phase", 1, required=True),
    Column(ALARMS, "alarms", 2, required=True),
    Column(PROGRESS, "progress", 3, required=True),
    Column(SOLVED, "solved", 4, justify="right", required=True),
    Column(LAG, "lag", 6, justify="right"),
    Column(DROPS, "drops", 5, justify="right", required=True),
    Column(RESTARTS, "restarts", 7, justify="right"),
    Column(BREAKDOWN, "drops by kind", 9),
    Column(DETAILS, "details", 8, flexible=True),
)
"""The status table's columns, left to right; `keep` ranks them for a narrow terminal: the process, its phase,
its alarms, its progress, the solve rate and the drops always stay, then the lag, the restarts, the rest of its
fields and, only when wide, the drops by kind."""

CELL_JOINS = {ALARMS: ", ", BREAKDOWN: ", ", DETAILS: " | "}
"""How the fields of one column are joined in its cell (the others hold one field each)."""


class Part(NamedTuple):
    """One field of a process's status: as its plain line says it, and in which column and how the table shows
    it."""

    text: str
    """As the plain line says it ("" for a field only the table shows)."""
    column: str = DETAILS
    cell: str | None = None
    """As the table's cell says it (None: `text`)."""


StatusParts = Callable[[str, dict[str, Any], Mapping[str, Any]], list[Part]]
"""A role's reading of one process's status into fields, from its name, its status and every process's newest
status (an actor's row shows the lag the learner reports for it)."""


def _body(parts: list[Part]) -> str:
    """The plain line of a process's fields: every text, in order, " | " between them."""
    return " | ".join(part.text for part in parts if part.text)


def alarm_parts(status: dict[str, Any]) -> list[Part]:
    """What needs a person's eye: updates skipped as non-finite, a learner whose batches are all stale, several
    learner instances seen by a follower, a follower that had to re-sync. Early in a plain line and in a column
    of their own that a narrow terminal still shows."""
    alarms = []
    if _count_of(status, "skipped_non_finite"):
        count = status["skipped_non_finite"]
        alarms.append(Part(f"SKIPPED {count} non-finite updates", ALARMS, f"SKIPPED {count} non-finite"))
    if _count_of(status, "stale_streak") >= STALE_SHOWN_AFTER:
        count = status["stale_streak"]
        alarms.append(Part(f"last {count} batches ALL STALE", ALARMS, f"{count} ALL STALE"))
    if _count_of(status, "learners_seen") > 1:
        count = status["learners_seen"]
        alarms.append(Part(f"{count} LEARNERS on the bus", ALARMS, f"{count} LEARNERS"))
    if _count_of(status, "resyncs"):
        alarms.append(Part(f"re-synced {status['resyncs']}x", ALARMS))
    return alarms


def alarms_part(status: dict[str, Any]) -> str:
    """The alarms of `status` as its plain line has them, each after " | " ("" when all is well)."""
    return "".join(f" | {part.text}" for part in alarm_parts(status))


def _count_of(status: dict[str, Any], key: str) -> int:
    value = status.get(key)
    return value if isinstance(value, int) and not isinstance(value, bool) else 0


def phase_parts(status: dict[str, Any], usual: str) -> list[Part]:
    """The phase a status says its process is in (`phase`, with its seconds so far when it says since when:
    `phase_since`, a wall-clock time), `usual` when it says none. The plain line names it only when it is not the
    usual one."""
    phase = status.get("phase")
    if not isinstance(phase, str) or not phase:
        return [Part("", PHASE, usual)]
    since = status.get("phase_since")
    if isinstance(since, int | float) and not isinstance(since, bool):
        phase = f"{phase} {max(time.time() - since, 0):.0f} s"
    return [Part("" if phase == usual else phase, PHASE, phase)]


LEARNER_DROPS = (("stale", "dropped_stale"), ("old-epoch", "dropped_old_epoch"), ("overflow", "dropped_overflow"),
                 ("inbox-full", "dropped_inbox_full"), ("lost", "lost"))


def learner_parts(status: dict[str, Any]) -> list[Part]:
    """The learner's fields: policy version and epoch, alarms, phase, updates, rates, queue, drops and refusals,
    the training solve rate, the newest evaluation."""
    drops = " ".join(f"{label} {status.get(key, 0)}" for label, key in LEARNER_DROPS)
    rejected = _total(status.get("rejected"))
    dropped = sum(_count_of(status, key) for _, key in LEARNER_DROPS)
    solved = _number(status.get("solve_rate"), "{:.0%}")
    return [Part(f"v{status['policy_version']} epoch {status['epoch']}"), *alarm_parts(status),
            *phase_parts(status, "training"),
            Part(f"update {status['update']:,}/{status['num_updates']:,}", PROGRESS),
            Part(f"{_number(status.get('updates_per_s'), '{:.2f}')} upd/s"),
            Part(f"{_number(status.get('consumed_steps_per_s'))} steps/s consumed"),
            Part(f"queue {status.get('queue', 0)}"),
            Part(f"dropped {drops}", BREAKDOWN, drops), Part(f"rejected {rejected}", BREAKDOWN),
            Part(f"solved {solved}", SOLVED, solved), Part("", DROPS, f"{dropped + rejected:,}"),
            *_evaluation_parts(status.get("evaluation"))]


def learner_line(status: dict[str, Any] | None) -> str:
    return STARTING if status is None else _body(learner_parts(status))


def _evaluation_parts(evaluation: Any) -> list[Part]:
    """The learner's newest evaluation ([] before the first)."""
    if not isinstance(evaluation, dict) or "policy_version" not in evaluation:
        return []
    return [Part(f"eval v{evaluation['policy_version']} {_number(evaluation.get('mean'), '{:.0%}')}")]


def actor_parts(status: dict[str, Any], lag: int | None) -> list[Part]:
    """An actor's fields: steps/s, policy version, alarms, lag, batches in flight, drops and refusals, its levels,
    what it waits for (its phase: acting otherwise), the batches it sent, what it streams."""
    waiting = f"waiting for {status['waiting']}" if status.get("waiting") else ""
    lag_text = "-" if lag is None else str(lag)
    dropped, written_off = status.get("dropped_no_credit", 0), status.get("written_off", 0)
    rejected = _total(status.get("rejected"))
    sent = f"{_count_of(status, 'sent'):,} batches" if "sent" in status else ""
    total = _count_of(status, "dropped_no_credit") + _count_of(status, "written_off") + rejected
    return [Part(f"{_number(status.get('steps_per_s'))} steps/s"), Part(f"v{status['policy_version']}"),
            *alarm_parts(status), Part(f"lag {lag_text}", LAG, lag_text),
            Part(f"in flight {status.get('in_flight', 0)}"),
            Part(f"dropped {dropped} written off {written_off}", BREAKDOWN),
            Part(f"rejected {rejected}", BREAKDOWN), Part(f"levels {status.get('levels', '?')}"),
            Part(waiting, PHASE, waiting or "acting"), Part("", PROGRESS, sent), Part("", DROPS, f"{total:,}"),
            *_streaming_parts(status.get("monitor"))]


def actor_line(status: dict[str, Any] | None, lag: int | None) -> str:
    return STARTING if status is None else _body(actor_parts(status, lag))


def evaluator_parts(status: dict[str, Any]) -> list[Part]:
    """The evaluator's fields: the newest policy it holds, the last one it scored and how, what it skipped; while
    it scores, which policy, on how many levels, for how long (its phase)."""
    scoring = phase_parts(status, "evaluating") if status.get("phase") else []
    if status.get("scored_version") is None:
        held = status.get("policy_version", -1)
        if held < 0:
            return [Part("waiting for the learner's weights", PHASE, "waiting for weights")]
        return [Part(f"v{held}"), *(scoring or [Part("scoring its first policy", PHASE, f"scoring v{held}")])]
    groups = " ".join(f"{name} {rate:.0%}" for name, rate in sorted(status.get("groups", {}).items()))
    mean = _number(status.get("mean"), "{:.0%}")
    seconds = _number(status.get("seconds"), "{:.1f}")
    rejected = _total(status.get("rejected"))
    return [Part(f"v{status['policy_version']}"), *alarm_parts(status),
            Part(f"scored v{status['scored_version']}: mean {mean}{' ' + groups if groups else ''} in {seconds} s",
                 cell=f"{groups + ' ' if groups else ''}in {seconds} s"),
            Part(f"{status.get('evaluations', 0)} evaluations, {status.get('skipped', 0)} points skipped"),
            Part(f"rejected {rejected}", BREAKDOWN), *(scoring or [Part("", PHASE, "evaluating")]),
            Part("", PROGRESS, f"scored v{status['scored_version']}"), Part("", SOLVED, mean),
            Part("", DROPS, f"{rejected:,}")]


def evaluator_line(status: dict[str, Any] | None) -> str:
    """The evaluator's line: the newest policy it holds, the last one it scored and how, what it skipped."""
    return STARTING if status is None else _body(evaluator_parts(status))


def recorder_parts(status: dict[str, Any]) -> list[Part]:
    """The recorder's fields: what it has written, what waits for the next shard, what it had to leave out."""
    full = bool(status.get("full"))
    episodes, steps = status.get("episodes_written", 0), status.get("steps_written", 0)
    shards = f"{status.get('shards_written', 0)} shards, {status.get('bytes_used', 0) / 1e6:.1f} MB"
    rejected, cut = _total(status.get("rejected")), status.get("episodes_cut", 0)
    parts = [Part(f"{episodes:,} episodes ({steps:,} steps) in {shards}", cell=f"{steps:,} steps in {shards}"),
             Part(f"waiting {status.get('pending_steps', 0):,} steps"), Part(f"cut {cut}", BREAKDOWN),
             Part(f"rejected {rejected}", BREAKDOWN)]
    if full:
        parts.append(Part("FULL: recording stopped", ALARMS, "FULL"))
    return [*parts, Part("", PHASE, "stopped: full" if full else "recording"),
            Part("", PROGRESS, f"{episodes:,} episodes"),
            Part("", DROPS, f"{_count_of(status, 'episodes_cut') + rejected:,}")]


def recorder_line(status: dict[str, Any] | None) -> str:
    """The recorder's line: what it has written, what waits for the next shard, what it had to leave out."""
    return STARTING if status is None else _body(recorder_parts(status))


def _streaming_parts(monitor: dict[str, Any] | None) -> list[Part]:
    if not monitor:
        return []
    if not monitor.get("viewer"):
        return [Part("stream: no viewer")]
    return [Part(f"stream: {monitor.get('frames_logged', 0):,} frames, {monitor.get('rollouts_dropped', 0)} rollouts "
                 "dropped")]


def streaming_part(monitor: dict[str, Any] | None) -> str:
    """What an actor streams to Rerun, for its status line ("" when monitoring is off)."""
    return "".join(f" | {part.text}" for part in _streaming_parts(monitor))


def curriculum_parts(status: dict[str, Any]) -> list[Part]:
    """The curriculum service's fields: its method, its buffer, what it staged, served and heard, drops and
    refusals, batch-scored SFL's refills (its phase: serving, scoring levels with the count, holding level
    requests)."""
    rejected = _total(status.get("rejected"))
    dropped = status.get("dropped_inbox_full", 0)
    phase = (f"scoring levels{scoring_part(status).removeprefix(', scoring')}" if status.get("scoring") else
             "holding level requests" if status.get("filling") else "serving")
    return [Part(str(status.get("method", "?"))),
            Part(f"buffer {_number(status.get('buffer_fill'), '{:.0%}')} full, score "
                 f"{_number(status.get('score_mean'), '{:.3f}')}, learnable "
                 f"{_number(status.get('learnable'), '{:.0%}')}"),
            Part(f"staged {status.get('staged', 0)}"), Part(f"served {status.get('samples', 0):,}", PROGRESS),
            Part(f"results {status.get('results', 0):,}"), Part(f"dropped {dropped}", BREAKDOWN),
            Part(f"rejected {rejected}", BREAKDOWN), *_refill_parts(status), Part("", PHASE, phase),
            Part("", DROPS, f"{_count_of(status, 'dropped_inbox_full') + rejected:,}")]


def curriculum_line(status: dict[str, Any] | None) -> str:
    return STARTING if status is None else _body(curriculum_parts(status))


def _refill_parts(status: dict[str, Any]) -> list[Part]:
    """Batch-scored SFL's refills ([] for the other curricula)."""
    if "refills" not in status:
        return []
    last = status.get("last_refill") or {}
    newest = f" (v{last['version']}, {last.get('seconds', 0):.0f} s)" if "version" in last else ""
    filling = ", holding level requests" if status.get("filling") else ""
    return [Part(f"refills {status['refills']}{newest}{scoring_part(status)}{filling}")]


def scoring_part(status: dict[str, Any]) -> str:
    """", scoring 1,024/2,048" while batch-scored SFL scores candidates (the count once its first block is
    done), "" otherwise."""
    if not status.get("scoring"):
        return ""
    done, total = (status.get("scored_candidates") or [0, 0])[:2]
    return f", scoring {done:,}/{total:,}" if total else ", scoring"


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


class ProcessRow(NamedTuple):
    """One process of the display: its plain line (not yet cut to a width), its table cells, and the line shown
    below the table for it (an exited process's state and error line), if any."""

    line: str
    cells: dict[str, Text | str]
    note: str | None = None


PHASE_STYLES = (("starting", "yellow"), ("compiling", "yellow"), ("waiting", "yellow"), ("stopping", "yellow"),
                ("checkpointing", "cyan"), ("evaluating", "cyan"), ("exited", "red"), ("cannot run", "red"),
                ("malformed", "red"), ("stopped", "red"))
"""Colours of the phases that are not steady work, by how they begin."""


def _cells(name: str, restarts: int | None, parts: list[Part]) -> dict[str, Text | str]:
    """The table cells of one process: its fields gathered by column (several in a column joined by
    `CELL_JOINS`), the phase coloured by kind and the alarms in bold red."""
    gathered: dict[str, list[str]] = {}
    for part in parts:
        cell = part.text if part.cell is None else part.cell
        if cell:
            gathered.setdefault(part.column, []).append(cell)
    cells: dict[str, Text | str] = {key: CELL_JOINS.get(key, " ").join(texts) for key, texts in gathered.items()}
    cells[PROCESS] = name
    for always in (PROGRESS, SOLVED, DROPS):  # their columns stay on screen from the first row on
        cells.setdefault(always, "-")
    if restarts is not None:
        cells[RESTARTS] = str(restarts)
    phase = str(cells.get(PHASE, ""))
    style = next((style for start, style in PHASE_STYLES if phase.startswith(start)), "green")
    cells[PHASE] = Text(phase, style=style)
    if cells.get(ALARMS):
        cells[ALARMS] = Text(str(cells[ALARMS]), style="bold red")
    return cells


def _cut(line: str, columns: int) -> str:
    """`line` no wider than `columns` ("..." marks a cut), so a redrawn block never wraps."""
    return line if len(line) <= columns else line[:max(columns - 3, 0)] + "..."


class StatusBlock:
    """What the display shows at one moment: a row per process. Drawn by rich as a table that fits the width it
    is given (the terminal's), with the exited processes' error lines below it; `lines` gives the plain lines."""

    def __init__(self, rows: list[ProcessRow]) -> None:
        self.rows = rows

    def lines(self, columns: int | None = None) -> list[str]:
        """The plain lines, each cut to `columns` (default: the terminal's width, else COLUMNS_WITHOUT_TERMINAL)."""
        if columns is None:
            columns = shutil.get_terminal_size((COLUMNS_WITHOUT_TERMINAL, 24)).columns
        return [_cut(row.line, columns) for row in self.rows]

    def table(self, width: int) -> RenderableType:
        """The table no wider than `width`, and below it a line per process with an error line to show."""
        notes = [Text(row.note, style="red", no_wrap=True, overflow="ellipsis") for row in self.rows if row.note]
        return Group(fitted_table(TABLE_COLUMNS, [row.cells for row in self.rows], width), *notes)

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        yield self.table(options.max_width)


def _exited_phase(child: Child) -> str:
    """The phase of a child that is not running: that it exited, how, and what happens next."""
    if child.last_exit is None:
        return "stopped"
    if child.gave_up and child.last_exit == EXIT_CANNOT_RUN:
        return "exited: cannot run"
    if child.gave_up:
        return "exited, gave up"
    if child.restart_at is not None:
        return f"exited, restarting in {max(child.restart_at - time.monotonic(), 0):.0f} s"
    return "exited" if child.last_exit == 0 else f"exited: {describe_exit(child.last_exit)}"


def status_block(statuses: dict[str, dict[str, Any]], children: list[Child],
                 parts: Mapping[str, StatusParts | None], stopping: Collection[str] = ()) -> StatusBlock:
    """Every child with its process state, then its latest status (`current_status`), read into fields by its
    role's reader in `parts` (by child name; None for a process that publishes no status, such as the viewer:
    `deploy.runtime.process_roles.parts_by_child`); the children in `stopping` are being stopped by the launcher."""
    width = max(len(c.name) for c in children)
    rows = []
    for child in children:
        if child.pid is None:
            state = exited_state(child)
            rows.append(ProcessRow(f"{child.name:<{width}}  {state}",
                                   _cells(child.name, child.restarts, [Part("", PHASE, _exited_phase(child))]),
                                   f"{child.name}  {state}" if child.error_line or child.gave_up else None))
            continue
        status = current_status(child, statuses.get(child.name))
        read = parts.get(child.name)
        try:
            if read is None:
                fields = [Part(f"no status of its own (its log: {child.log_path})"), Part("", PHASE, "running")]
            elif status is None:  # nothing heard yet: say how long it has been
                elapsed = time.monotonic() - child.started_at
                fields = [Part(starting_part(elapsed), PHASE, f"starting {elapsed:.0f} s")]
            else:
                fields = read(child.name, status, statuses)
            body = _body(fields)
        except (TypeError, ValueError, KeyError, AttributeError):  # a status frame with fields of the wrong types
            fields = [Part("malformed status", PHASE)]
            body = "malformed status"
        if child.name in stopping:  # the launcher's word over the process's own
            fields = [part for part in fields if part.column != PHASE] + [Part("", PHASE, "stopping")]
        rows.append(ProcessRow(f"{child.name:<{width}}  pid {child.pid} restarts {child.restarts} | {body}",
                               _cells(child.name, child.restarts, fields)))
    return StatusBlock(rows)


def render(statuses: dict[str, dict[str, Any]], children: list[Child], parts: Mapping[str, StatusParts | None],
           columns: int | None = None) -> list[str]:
    """The display's plain lines (a log's): every child with its process state, then its latest status (the line
    of a child that has exited ends with its error line), each cut to `columns` (default: the terminal's width)."""
    return status_block(statuses, children, parts).lines(columns)


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


class StatusDisplay:
    """Shows status blocks (`status_block`, or plain lines). On a terminal: a live table at the bottom of the
    screen, redrawn in place every `redraw_every_s` seconds, with whatever else the process prints (its log lines)
    scrolling above it while the display is entered (`with display:`); outside a `with`, nothing else may write to
    the terminal while it is shown. Otherwise (a log file, CI): the plain lines as one log record every
    `log_every_s` seconds."""

    def __init__(self, stream: TextIO | None = None, redraw_every_s: float = 1.0, log_every_s: float = 10.0,
                 columns: int | None = None):
        """`columns`: the terminal's width to draw in (default: its own, as it is resized)."""
        self.stream = stream or sys.stdout
        self.columns = columns
        self.interactive = interactive(self.stream)
        self.every_s = redraw_every_s if self.interactive else log_every_s
        self._last = -float("inf")
        self._shown: RenderableType = Text("")
        self._live: LiveArea | None = None
        self._entered = False

    def __enter__(self) -> StatusDisplay:
        self._entered = True
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def due(self) -> bool:
        return time.monotonic() - self._last >= self.every_s

    def show(self, block: StatusBlock | list[str]) -> None:
        """Show `block` now: redrawn on a terminal, logged otherwise."""
        self._last = time.monotonic()
        if not self.interactive:
            lines = block.lines() if isinstance(block, StatusBlock) else block
            log.info("status\n  %s", "\n  ".join(lines))
            return
        self.redraw(block)

    def redraw(self, block: StatusBlock | list[str]) -> None:
        """On a terminal, draw `block` in place of the last one now (off a terminal, nothing: a log gets a block
        every `log_every_s`, from `show`)."""
        if not self.interactive:
            return
        self._shown = block if isinstance(block, StatusBlock) else Group(
            *(Text(line, no_wrap=True, overflow="ellipsis") for line in block))
        if self._live is None:
            self._live = LiveArea(self.stream, lambda: self._shown, auto_refresh=False, redirect=self._entered,
                                  width=self.columns)
            self._live.start()
        else:
            self._live.refresh()

    def close(self) -> None:
        """Stop redrawing; the last block stays on the screen, above whatever is printed next."""
        if self._live is not None:
            self._live.stop()
            self._live = None
