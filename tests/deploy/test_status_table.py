"""The status table of `impulse launch` and the progress row of `impulse train` fit the terminal, keeping what
matters (`deploy.runtime.status_display`, `deploy.runtime.progress`), and the plain lines a log gets keep their
words; the heartbeat of a long phase speaks off a terminal. Drawn by rich into strings and a pyte screen, in this
process: no processes, no JAX programs."""

from __future__ import annotations

import io
import logging
import time
from pathlib import Path

import pyte
import pytest
from rich.console import Console
from rich.text import Text

from impulse.deploy.runtime import status_display
from impulse.deploy.runtime.process_roles import parts_by_child
from impulse.deploy.runtime.progress import (
    PROGRESS_COLUMNS,
    SKIPPED_NON_FINITE,
    Heartbeat,
    ProgressLine,
    fitted_table,
)
from impulse.deploy.runtime.status_display import StatusDisplay, render, status_block
from impulse.deploy.runtime.supervisor import Child


class _Running:
    """Stands for a child's running process (`Child.pid` asks it)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid

    def poll(self) -> None:
        return None


def _child(name: str, pid: int | None, restarts: int = 0) -> Child:
    child = Child(name, lambda restart: [], Path("/nonexistent") / f"{name}.log")
    if pid is not None:
        child.process = _Running(pid)  # type: ignore[assignment]
    child.started_at, child.started_wall, child.restarts = time.monotonic() - 15, time.time() - 15, restarts
    return child


def _run() -> tuple[dict, list[Child]]:
    """A learner in its final evaluation with an alarm, an actor waiting for credit, one starting, a curriculum
    service, and an actor that died and waits for its restart."""
    dead = _child("actor-2", None)
    dead.last_exit, dead.restart_at = 1, time.monotonic() + 4.2
    dead.error_line = "ValueError: the rollout failed " + "x" * 120
    children = [_child("learner", 101), _child("curriculum", 102), _child("actor-0", 103), _child("actor-1", 104, 1),
                dead]
    statuses = {
        "learner": {"policy_version": 25, "epoch": 1, "update": 25, "num_updates": 977, "updates_per_s": 0.26,
                    "consumed_steps_per_s": 1065.0, "queue": 1, "solve_rate": 0.42, "rejected": {"stale": 2},
                    "dropped_stale": 1, "actor_lag": {"actor-0": 1}, "skipped_non_finite": 2,
                    "phase": "evaluating 42 levels x 20 attempts", "phase_since": time.time() - 12},
        "curriculum": {"method": "sfl", "buffer_fill": 0.5, "score_mean": 0.1, "learnable": 0.3, "samples": 120,
                       "results": 7, "dropped_inbox_full": 0, "rejected": {}},
        "actor-0": {"steps_per_s": 2561.0, "policy_version": 24, "in_flight": 1, "dropped_no_credit": 0,
                    "written_off": 1, "rejected": {}, "levels": "handmade:s_easy_car_right (1 level)",
                    "waiting": "credit", "sent": 40},
    }
    return statuses, children


def _drawn(renderable, columns: int) -> list[str]:
    console = Console(file=io.StringIO(), width=columns, force_terminal=False)
    console.print(renderable)
    return console.file.getvalue().splitlines()


@pytest.mark.parametrize("columns", [80, 120, 200])
def test_the_status_table_fits_the_terminal_keeping_what_matters_first(columns: int) -> None:
    statuses, children = _run()
    lines = _drawn(status_block(statuses, children, parts_by_child(children)), columns)
    assert all(len(line) <= columns for line in lines), lines
    header, *rows = lines
    for shown in ("process", "phase", "alarms", "progress", "solved", "drops"):
        assert shown in header.split(), (shown, header)
    learner, curriculum, actor, starting, dead, note = rows
    assert learner.split()[:2] == ["learner", "evaluating"] and "SKIPPED 2" in learner and "42%" in learner
    assert "update 25/977" in learner and "3" in learner.split(), learner  # 1 dropped + 2 refused
    assert "waiting for credit" in actor and "40 batches" in actor
    assert "starting 15 s" in starting and curriculum.split()[1] == "serving"
    assert dead.split()[:2] == ["actor-2", "exited,"]
    assert note.startswith("actor-2  exit status 1; restarting in 4 s (restarts 0) | ValueError")
    if columns >= 120:
        assert {"lag", "restarts"} <= set(header.split()), header
        assert "evaluating 42 levels x 20 attempts 12 s" in learner
    if columns >= 200:
        assert "drops by kind" in header and "details" in header and "stale 1 old-epoch 0" in learner


def test_a_process_being_stopped_shows_it_and_an_exited_one_how_it_ended() -> None:
    statuses, children = _run()
    block = status_block(statuses, children, parts_by_child(children), stopping={"actor-0"})
    actor = next(line for line in _drawn(block, 120) if line.startswith("actor-0"))
    assert actor.split()[1] == "stopping", actor
    done = _child("actor-3", None)
    done.last_exit = 0
    [header, row] = _drawn(status_block({}, [done], parts_by_child([done])), 80)
    assert row.split()[:2] == ["actor-3", "exited"], row


def test_the_plain_lines_of_a_log_keep_their_words_and_name_a_phase_out_of_the_ordinary() -> None:
    statuses, children = _run()
    lines = render(statuses, children, parts_by_child(children), columns=300)
    assert lines[0].startswith("learner     pid 101 restarts 0 | v25 epoch 1 | SKIPPED 2 non-finite updates | "
                               "evaluating 42 levels x 20 attempts 12 s | update 25/977 | 0.26 upd/s"), lines[0]
    assert lines[2].endswith("| levels handmade:s_easy_car_right (1 level) | waiting for credit"), lines[2]
    assert "starting for 15 s (importing JAX, compiling" in lines[3]
    assert lines[4].startswith("actor-2     exit status 1; restarting in 4 s")
    training = {**statuses["learner"], "phase": "training"}
    del training["phase_since"]
    assert "training" not in status_display.learner_line(training)  # the usual phase goes unsaid


class Terminal(io.StringIO):
    """Captured output that says it is a terminal, as the launcher's stderr is in a shell."""

    def isatty(self) -> bool:
        return True


def fake_terminal(monkeypatch) -> Terminal:
    monkeypatch.setenv("TERM", "xterm")
    return Terminal()


def test_an_entered_display_on_a_terminal_redraws_the_table_in_place(monkeypatch) -> None:
    statuses, children = _run()

    terminal = fake_terminal(monkeypatch)
    with StatusDisplay(stream=terminal, columns=80) as display:
        for update in (25, 26, 27):
            statuses["learner"]["update"] = update
            display.show(status_block(statuses, children, parts_by_child(children)))
    screen = pyte.Screen(80, 20)
    pyte.Stream(screen).feed(terminal.getvalue().replace("\n", "\r\n"))
    shown = [line.rstrip() for line in screen.display if line.strip()]
    assert [line.split()[0] for line in shown] == ["process", "learner", "curriculum", "actor-0", "actor-1",
                                                   "actor-2", "actor-2"], shown
    assert "update 27/977" in shown[1]


def test_the_progress_row_keeps_its_phase_update_solve_rate_and_alarm_at_80_columns() -> None:
    cells = {"phase": "checkpointing 3 s", "update": "12/30", "steps_per_s": "2,345", "eta": "0:45",
             "solved": "26%", "skipped": Text("3 non-finite"), "return": "0.123", "episodes": "1,234"}
    for columns in (40, 80):
        header, row = _drawn(fitted_table(PROGRESS_COLUMNS, [cells], columns), columns)
        assert all(word in header.split() for word in ("phase", "update", "solved", "skipped")), header
        assert len(row) <= columns and "12/30" in row and "26%" in row


def test_the_progress_line_off_a_terminal_logs_as_before(caplog) -> None:
    line = ProgressLine(640, stream=io.StringIO(), log_every_s=0, num_updates=10)
    with caplog.at_level(logging.INFO):
        line.phase("checkpointing")
        line.update(128, 1000.0, {"solve_rate": 0.5}, record={"update": 2, SKIPPED_NON_FINITE: 1.0})
        line.close("done")
    assert "progress 128/640 steps | 1,000 steps/s | ETA 0:00 | solved 50% | SKIPPED 1 non-finite updates" \
        in caplog.text, caplog.text


def test_the_skipped_column_is_the_learners() -> None:
    from impulse.learner.non_finite import SKIPPED_COLUMN

    assert SKIPPED_NON_FINITE == SKIPPED_COLUMN


def test_a_heartbeat_off_a_terminal_says_its_first_phase_then_that_a_quiet_one_still_runs(caplog) -> None:
    with caplog.at_level(logging.INFO), Heartbeat("loading", stream=io.StringIO(), every_s=0.2) as beat:
        time.sleep(0.05)
        beat.phase("compiling the evaluation")
        time.sleep(1.6)  # the beat looks every 0.2 s here
    said = [record.getMessage() for record in caplog.records]
    assert said[0] == "loading ...", said
    assert any(message.startswith("compiling the evaluation: ") and message.endswith(" s so far")
               for message in said), said
    assert not any(message.startswith("loading:") for message in said), "a phase changed before its beat is quiet"


def test_an_evaluator_that_is_scoring_says_on_how_many_levels_and_for_how_long() -> None:
    scored = {"policy_version": 9, "scored_version": 6, "evaluations": 2, "skipped": 0, "seconds": 41.0,
              "mean": 0.25, "groups": {"kinetix:s": 0.25}, "levels": 74, "rejected": {}}
    assert "| evaluating |" not in status_display.evaluator_line(scored)  # between scorings: the usual phase
    scoring = {**scored, "phase": "evaluating 74 levels x 20 attempts", "phase_since": time.time() - 30,
               "scoring_version": 9}
    line = status_display.evaluator_line(scoring)
    assert "evaluating 74 levels x 20 attempts 30 s" in line and "scored v6: mean 25%" in line, line
    first = {**scoring, "scored_version": None}
    assert "evaluating 74 levels x 20 attempts 30 s" in status_display.evaluator_line(first)
    assert "scoring its first policy" in status_display.evaluator_line({**first, "phase": None})


def test_log_lines_scroll_above_the_table_and_leave_no_stale_block(monkeypatch) -> None:
    """The launcher's way of drawing: 24 log lines, each followed by a redraw, on an 80 x 40 terminal whose stderr
    the log handler writes to. At the end the screen holds one table, at the bottom, and the newest log lines, in
    order, above it: no block of an earlier drawing is left between them."""
    statuses, children = _run()

    terminal = fake_terminal(monkeypatch)
    monkeypatch.setattr("sys.stderr", terminal)
    handler = logging.StreamHandler(terminal)  # as `impulse launch` logs: a root handler on stderr
    handler.setFormatter(logging.Formatter("%(message)s"))
    root = logging.getLogger()
    # Only this handler: an in-process `impulse` call earlier in the worker may have left one on a closed stream.
    kept = root.handlers[:]
    root.handlers = [handler]
    logger = logging.getLogger("tests.status_table.scroll")
    try:
        with StatusDisplay(stream=terminal, columns=80) as display:
            for line in range(24):
                statuses["learner"]["update"] = 25 + line
                display.show(status_block(statuses, children, parts_by_child(children)))
                logger.warning("log line %02d", line)
            display.show(status_block(statuses, children, parts_by_child(children)))
    finally:
        root.handlers = kept
    screen = pyte.Screen(80, 40)
    pyte.Stream(screen).feed(terminal.getvalue().replace("\n", "\r\n"))
    shown = [line.rstrip() for line in screen.display if line.strip()]
    headers = [i for i, line in enumerate(shown) if line.split()[:2] == ["process", "phase"]]
    assert len(headers) == 1, "\n".join(shown)
    logged = shown[:headers[0]]
    assert len(logged) >= 20 and all(line.startswith("log line") for line in logged), "\n".join(shown)
    assert logged == [f"log line {n:02d}" for n in range(24 - len(logged), 24)], "\n".join(shown)
    assert "update 48/977" in shown[headers[0] + 1], "\n".join(shown)
