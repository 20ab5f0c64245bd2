"""The launcher's supervisor with real child processes (`python -c ...`): a child that fails the same way three
times in a row is given up on, with its error line; one that fails differently each time, or is killed from
outside, is restarted; the status display shows how each ended. Back-offs are injected so each test takes about
a second."""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path

import pytest

from impulse.deploy.runtime.exit_codes import EXIT_CANNOT_RUN
from impulse.deploy.runtime.process_roles import parts_by_child
from impulse.deploy.runtime.status_display import StatusDisplay, render
from impulse.deploy.runtime.supervisor import Child, Supervisor, error_line, is_failure

FAST = {"give_up_after": 3, "backoff_s": (0.05,)}


def child(tmp_path: Path, code: str, name: str = "actor-0") -> Child:
    return Child(name, lambda restart: [sys.executable, "-c", code], tmp_path / "logs" / f"{name}.log")


def drive(supervisor: Supervisor, until, timeout_s: float = 30.0) -> None:
    """What the launcher's loop does with its children (restart those that exited, unless given up on) until
    `until()` holds."""
    deadline = time.monotonic() + timeout_s
    while not until():
        assert time.monotonic() < deadline, "timed out"
        for ended, _ in supervisor.exited():
            if not ended.gave_up:
                supervisor.restart_later(ended)
        supervisor.restart_due()
        time.sleep(0.01)


def counter(tmp_path: Path) -> str:
    """Python source that counts this child's starts in a file and sets `n` to this start's number."""
    path = tmp_path / "starts"
    return (f"import pathlib; p = pathlib.Path({str(path)!r}); n = int(p.read_text()) + 1 if p.exists() else 1; "
            "p.write_text(str(n))\n")


@pytest.mark.heavy
def test_a_child_that_fails_the_same_way_is_given_up_after_three(tmp_path: Path) -> None:
    failing = child(tmp_path, "print('loading levels', flush=True)\n"
                              "raise ValueError('/x/bad.json: not valid JSON: Expecting value')")
    supervisor = Supervisor([failing], **FAST)
    supervisor.start(failing.name)
    drive(supervisor, lambda: failing.gave_up)
    assert failing.history == [1, 1, 1] and failing.restarts == 2 and failing.streak == 3
    assert failing.error_line == "ValueError: /x/bad.json: not valid JSON: Expecting value"
    time.sleep(0.3)
    drive(supervisor, lambda: True)
    assert failing.pid is None and failing.restart_at is None and failing.restarts == 2, "restarted after giving up"
    assert failing.log_path.read_text().count("Traceback") == 3


@pytest.mark.heavy
def test_a_child_whose_configuration_cannot_run_is_given_up_at_once(tmp_path: Path) -> None:
    """However long it took to find out (stable_after_s=0: a slow start-up, such as a long compile)."""
    failing = child(tmp_path, "import sys\nprint('impulse learner: the update needs about 23.2 GiB', flush=True)\n"
                              f"sys.exit({EXIT_CANNOT_RUN})")
    supervisor = Supervisor([failing], give_up_after=3, backoff_s=(0.05,), stable_after_s=0.0)
    supervisor.start(failing.name)
    drive(supervisor, lambda: failing.gave_up)
    assert failing.history == [EXIT_CANNOT_RUN] and failing.restarts == 0
    assert failing.error_line == "impulse learner: the update needs about 23.2 GiB"


@pytest.mark.heavy
def test_a_child_that_fails_differently_each_time_is_restarted(tmp_path: Path) -> None:
    failing = child(tmp_path, counter(tmp_path) + "raise SystemExit(f'attempt {n}: no luck')")
    supervisor = Supervisor([failing], **FAST)
    supervisor.start(failing.name)
    drive(supervisor, lambda: len(failing.history) >= 5)
    assert not failing.gave_up and failing.streak == 1
    assert failing.error_line == f"attempt {len(failing.history)}: no luck"


@pytest.mark.heavy
def test_a_child_killed_from_outside_is_restarted(tmp_path: Path) -> None:
    """SIGKILL (a user, a test, the OOM killer) never counts, even when the child's last line is the same."""
    killed = child(tmp_path, "import os, signal\nprint('same last line', flush=True)\n"
                             "os.kill(os.getpid(), signal.SIGKILL)")
    supervisor = Supervisor([killed], **FAST)
    supervisor.start(killed.name)
    drive(supervisor, lambda: len(killed.history) >= 5)
    assert killed.history[:5] == [-signal.SIGKILL] * 5
    assert not killed.gave_up and killed.streak == 0 and killed.error_line is None


@pytest.mark.heavy
def test_a_crash_signal_counts_and_only_this_incarnations_output_is_read(tmp_path: Path) -> None:
    """SIGABRT is a crash; the first start's traceback is not the error line of the later, silent ones."""
    crashing = child(tmp_path, counter(tmp_path) + "import os\nif n == 1: raise RuntimeError('first start only')\n"
                               "os.abort()")
    supervisor = Supervisor([crashing], **FAST)
    supervisor.start(crashing.name)
    drive(supervisor, lambda: crashing.gave_up)
    assert crashing.history == [1, -signal.SIGABRT, -signal.SIGABRT, -signal.SIGABRT]
    assert crashing.error_line is None


@pytest.mark.heavy
def test_failures_after_a_stable_run_do_not_count(tmp_path: Path) -> None:
    failing = child(tmp_path, "raise SystemExit('the same every time')")
    supervisor = Supervisor([failing], give_up_after=2, backoff_s=(0.05,), stable_after_s=0.0)
    supervisor.start(failing.name)
    drive(supervisor, lambda: len(failing.history) >= 4)
    assert not failing.gave_up and failing.error_line == "the same every time"


def test_error_line_picks_the_exception_of_the_last_traceback() -> None:
    log = """14:02:11.123 INFO    impulse.actor: loading levels
Traceback (most recent call last):
  File "x.py", line 1, in <module>
    load()
engine.levels.kinetix_json.LevelFileError: /x/a.json: not valid JSON

The above exception was the direct cause of the following exception:

Traceback (most recent call last):
  File "x.py", line 3, in <module>
    main()
engine.levels.sets.LevelSetError: /x/bad.json: 2 problems:
  polygon[4].position missing
  circle[0].radius missing
14:02:12.456 INFO    impulse.actor: closing the bus
"""
    assert error_line(log) == "engine.levels.sets.LevelSetError: /x/bad.json: 2 problems:"
    assert error_line("14:02:11.123 ERROR   impulse.learner: no weights\n\n") == "ERROR   impulse.learner: no weights"
    assert error_line('{"ts": "2026-01-01T00:00:00.000Z", "level": "ERROR", "logger": "impulse.x", "msg": "gone"}\n') \
        == "ERROR impulse.x: gone"
    assert error_line("Fatal Python error: Segmentation fault\n\nCurrent thread 0x1:\n  File \"x.py\", line 2\n") \
        == "Fatal Python error: Segmentation fault"
    assert error_line("") is None
    assert is_failure(1) and is_failure(-signal.SIGSEGV) and is_failure(-signal.SIGABRT)
    assert not any(is_failure(code) for code in (0, -signal.SIGKILL, -signal.SIGTERM, -signal.SIGINT))


def test_the_status_display_shows_how_a_child_ended(tmp_path: Path) -> None:
    gave_up = child(tmp_path, "", "actor-0")
    gave_up.last_exit, gave_up.restarts, gave_up.streak, gave_up.gave_up = 1, 2, 3, True
    gave_up.error_line = "engine.levels.sets.LevelSetError: /x/bad.json: not valid JSON: " + "x" * 200
    waiting = child(tmp_path, "", "actor-1")
    waiting.last_exit, waiting.restart_at = -signal.SIGSEGV, time.monotonic() + 4.2
    waiting.error_line = "Fatal Python error: Segmentation fault"
    lines = render({}, [gave_up, waiting], parts_by_child([gave_up, waiting]), columns=140)
    assert lines[0].startswith("actor-0  exit status 1; gave up after 3 identical failures (restarts 2) | "
                               "engine.levels.sets.LevelSetError: /x/bad.json")
    assert len(lines[0]) == 140 and lines[0].endswith("...")
    assert lines[1] == ("actor-1  killed by SIGSEGV; restarting in 4 s (restarts 0) | Fatal Python error: "
                        "Segmentation fault")
    cannot = child(tmp_path, "", "learner")
    cannot.last_exit, cannot.gave_up, cannot.streak = EXIT_CANNOT_RUN, True, 1
    cannot.error_line = "impulse learner: the learner's update needs about 23.2 GiB"
    assert render({}, [cannot], parts_by_child([cannot]), columns=200) == [
        "learner  exit status 78; cannot run with this configuration (restarts 0) | impulse learner: the learner's "
        "update needs about 23.2 GiB"]


@pytest.mark.heavy
def test_a_process_that_has_said_nothing_yet_shows_how_long_it_has_been_starting(tmp_path: Path) -> None:
    quiet = child(tmp_path, "import time; time.sleep(30)", "actor-0")
    supervisor = Supervisor([quiet], **FAST)
    supervisor.start(quiet.name)
    try:
        quiet.started_at -= 42  # as if it had been compiling for 42 s
        [line] = render({}, [quiet], parts_by_child([quiet]), columns=200)
        assert line.startswith(f"actor-0  pid {quiet.pid} restarts 0 | starting for 42 s (importing JAX, compiling")
    finally:
        supervisor.stop([quiet.name], 5)


class _Terminal:
    """A pyte screen behind a file-like object that says it is a terminal, as the launcher's stdout is."""

    def __init__(self, columns: int) -> None:
        import pyte

        self.screen = pyte.Screen(columns, 12)
        self._stream = pyte.Stream(self.screen)

    def isatty(self) -> bool:
        return True

    def write(self, text: str) -> None:
        self._stream.feed(text.replace("\n", "\r\n"))  # a tty's output post-processing turns \n into \r\n

    def flush(self) -> None:
        pass


@pytest.mark.heavy
@pytest.mark.parametrize("columns", [80, 120])
def test_the_status_display_redraws_in_place_without_wrapping(tmp_path: Path, columns: int) -> None:
    children = [child(tmp_path, "import time; time.sleep(60)", name)
                for name in ("learner", "curriculum", "actor-0", "actor-1")]
    for running in children:
        running.start({})
    try:
        _check_redraws(children, columns)
    finally:
        for running in children:
            running.process.kill()
            running.process.wait()


def _check_redraws(children: list[Child], columns: int) -> None:
    learner = {"policy_version": 12, "epoch": 1, "update": 12, "num_updates": 1000, "updates_per_s": 0.5,
               "consumed_steps_per_s": 123456.0, "queue": 1, "solve_rate": 0.25, "rejected": {}}
    terminal = _Terminal(columns)
    display = StatusDisplay(stream=terminal)
    for update in (12, 13, 14):  # three redraws of the same block
        lines = render({"learner": {**learner, "update": update}}, children, parts_by_child(children), columns=columns)
        display.show(lines)
    shown = [row.rstrip() for row in terminal.screen.display]
    assert shown[:4] == [line.rstrip() for line in lines], shown  # in place: the last block on the first rows
    assert not any(shown[4:]), f"wrapped or stacked lines below the block: {shown[4:]}"
    assert all(len(line) <= columns for line in lines) and lines[0].endswith("...")
