"""What `impulse launch`, `impulse train` and `impulse eval` show a person: real commands under a
pseudo-terminal of 80 and 120 columns (`tests.support.terminal`), read back from a pyte screen.

The launch's status table fits 80 columns with the solve rate on screen, is redrawn in place with the log lines
above it (never a stale block: one table header on the screen at any time, no process shown as starting once it
runs), and shows the learner's final evaluation as its phase. `impulse train`'s progress row fits 120 columns, and
what it builds and compiles before the first update is shown meanwhile. `impulse eval` says what it does from its
first line, before the evaluation is even compiled, and while it compiles.

The launch uses TINY_BATCH (the learner's and the actor's programs are in the compilation cache from the other
launch tests), `impulse eval` plays the same levels as the launch's final evaluation (the same program), and
`impulse train` the README's quick run, whose training step tests/learner/test_learns.py compiles."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from impulse.deploy.cli import main
from tests.support.launch_procs import QUICK_LAUNCH, TINY_BATCH, free_port
from tests.support.paths import REPO
from tests.support.terminal import TerminalRun, run_in_terminal

pytestmark = pytest.mark.heavy

LEVELS = "handmade:s_easy_car_right,handmade:s_easy_thrust_right"
UPDATES = 3
PROCESSES = ("learner", "actor-0")
LOG_LINE = re.compile(r"^\d\d:\d\d:\d\d\.\d{3} ")


def _is_status_header(line: str) -> bool:
    return line.split()[:2] == ["process", "phase"]


def _rows_below_header(screen: list[str]) -> list[str]:
    """The rows of the status table drawn on `screen` (the lines right below its header), [] if none is drawn."""
    headers = [i for i, line in enumerate(screen) if _is_status_header(line)]
    return [line.rstrip() for line in screen[headers[-1] + 1:headers[-1] + 1 + len(PROCESSES)]] if headers else []


def _check_status_screens(run: TerminalRun, columns: int) -> None:
    screens = [*run.snapshots, run.screen]
    drawn = [screen for screen in screens if _rows_below_header(screen)]
    assert drawn, run.dump()
    running_since = None  # the first screen on which both processes showed a status of their own
    for index, screen in enumerate(screens):
        headers = [line for line in screen if _is_status_header(line)]
        assert len(headers) <= 1, "a stale status block stayed on the screen:\n" + "\n".join(screen)
        if not headers:
            continue
        header = headers[0]
        for column in ("phase", "progress", "solved", "drops"):
            assert column in header.split(), f"{column!r} not shown at {columns} columns: {header!r}"
        rows = _rows_below_header(screen)
        # One line per process, each whole: a row that wrapped would push its end onto the next one.
        assert [row.split()[0] for row in rows if row.split()] == list(PROCESSES), "\n".join(screen)
        if running_since is None and all(row.split()[1] != "starting" for row in rows):
            running_since = index
        if running_since is not None:
            stale = [line for line in screen if "starting" in line and not LOG_LINE.match(line)]
            assert not stale, f"shown as starting after both were running: {stale}\n" + "\n".join(screen)
    assert running_since is not None, run.dump()


def test_a_launch_on_an_80_column_terminal_then_eval_of_its_policy(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    run_dir = tmp_path / "terminal"
    argv = [sys.executable, "-m", "impulse.deploy.cli", "launch", "--config", str(QUICK_LAUNCH),
            f"run_dir={run_dir}", f"name={run_dir.name}", f"bus.hub=tcp/127.0.0.1:{free_port()}",
            "actors.num_actors=1", "checkpoint.every_updates=1000", f"total_env_steps={UPDATES * 8 * 8}",
            "eval.attempts=2", f"eval.levels={LEVELS}", *TINY_BATCH]
    run = run_in_terminal(argv, columns=80, rows=40, timeout_s=400)
    assert run.returncode == 0, run.dump()
    _check_status_screens(run, 80)
    assert any(row.startswith("learner") and "evaluating the final policy" in row
               for screen in run.snapshots for row in _rows_below_header(screen)), \
        "the learner's final evaluation was never shown as its phase:\n" + run.dump()
    logged = [line for line in run.screen if LOG_LINE.match(line)]
    assert len(logged) >= 8, run.dump()  # the log scrolled above the table, which stayed one
    assert any("evaluation of the final policy" in line for line in logged), run.dump()

    _check_eval_reports_progress_from_its_first_second(run_dir, capsys)


def _check_eval_reports_progress_from_its_first_second(run_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`impulse eval` (in this process, JAX loaded already; stderr is not a terminal, so log lines) on the launch's
    two levels: its first line is the heartbeat's, before the checkpoint is read; it names the evaluation before the
    evaluation is compiled; a compile or a run longer than the heartbeat's 5 s says it still runs meanwhile; the
    table comes last, on stdout."""
    capsys.readouterr()
    assert main(["eval", "--checkpoint", str(run_dir), "--levels", LEVELS, "--attempts", "2"]) == 0
    captured = capsys.readouterr()
    said = [line for line in captured.err.splitlines() if LOG_LINE.match(line)]

    def first(pattern: str) -> int:
        found = [i for i, line in enumerate(said) if re.search(pattern, line)]
        assert found, f"no line matching {pattern!r}:\n{captured.err}"
        return found[0]

    assert first(r"loading the checkpoint's configuration and the levels \.\.\.") == 0, captured.err
    evaluating = first(r"evaluating 2 levels x 2 attempts \(compiling, then 4 episodes\)")
    evaluated = first(r"evaluated 2 levels in [\d.]+ s")
    assert 0 < evaluating < evaluated, captured.err
    seconds = float(re.search(r"evaluated 2 levels in ([\d.]+) s", said[evaluated]).group(1))
    if seconds >= 6.0:  # long enough for the heartbeat to say that it still runs
        assert any("s so far" in line for line in said[evaluating:evaluated]), captured.err
    assert re.search(r"^level +solved +return +length", captured.out, re.MULTILINE), captured.out
    assert "s_easy_car_right" in captured.out and "s_easy_thrust_right" in captured.out, captured.out


def test_train_on_a_120_column_terminal_shows_its_phases_and_a_row_that_fits(tmp_path) -> None:
    argv = [sys.executable, "-m", "impulse.deploy.cli", "train", "--config", str(REPO / "configs" / "quick-cpu.toml"),
            f"run_dir={tmp_path / 'fused'}", f"total_env_steps={64 * 64}", "checkpoint.every_updates=1000",
            "eval.attempts=0"]
    run = run_in_terminal(argv, columns=120, rows=30, timeout_s=300)
    assert run.returncode == 0, run.dump()
    assert run.shown("building the environment and the network"), "the heartbeat before the network table"
    headers = 0
    for screen in [*run.snapshots, run.screen]:
        found = [i for i, line in enumerate(screen) if line.split()[:2] == ["phase", "update"]]
        assert len(found) <= 1, "\n".join(screen)
        if found:
            headers += 1
            header = screen[found[0]].split()
            assert {"steps/s", "ETA", "solved"} <= set(header), header
            row = screen[found[0] + 1].split()
            assert row and row[0] in ("training", "checkpointing", "done"), screen[found[0] + 1]
    assert headers, run.dump()
    final = [line.split() for line in run.screen]
    assert any(words[:2] == ["done", "1/1"] for words in final), run.dump()
