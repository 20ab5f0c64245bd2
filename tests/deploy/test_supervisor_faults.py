"""The launcher's supervisor when things go wrong (`deploy.runtime.supervisor`, `deploy.runtime.status_display`):
a child's error line is one line and never a piece of a traceback, whatever its log's tail holds (chained
tracebacks, one cut short by a full disk, threads' lines in between, JSON lines); children are started without
running the parent's at-fork hooks (JAX warns in them) and still die with the parent; a restarted child's line
says "starting" until its own first status, never its dead predecessor's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from impulse.deploy.runtime import status_display
from impulse.deploy.runtime.process_roles import parts_by_child
from impulse.deploy.runtime.status_display import render
from impulse.deploy.runtime.supervisor import (
    CUT_SHORT,
    GUARD,
    MAX_ERROR_LINE,
    PARENT_PID_ENV,
    Child,
    Supervisor,
    error_line,
)
from impulse.engine.io_errors import lift_write_limits, limit_writes

CHAINED = """\
14:02:11.123 INFO    impulse.learner: compiling the update
Traceback (most recent call last):
  File "/work/main/monitor/scalars.py", line 84, in write_scalars
    writer.flush()
OSError: [Errno 28] No space left on device

During handling of the above exception, another exception occurred:

Traceback (most recent call last):
  File "/work/main/deploy/runtime/runloop.py", line 188, in run_loop
    sink.write(last)
    ^^^^^^^^^^^^^^^^
  File "/work/main/monitor/scalars.py", line 108, in write
    write_scalars(self.writer, record)
RuntimeError: the event file could not be written
14:02:12.456 INFO    impulse.bus: closing the session
"""

CUT_SHORT_AFTER_A_LOG_LINE = """\
14:02:11.123 INFO    impulse.learner: update 12 of 40
14:02:11.200 ERROR   impulse.run: the metrics row of update 13: no space left on device writing /run/x/metrics.jsonl
--- Logging error ---
Traceback (most recent call last):
  File "/usr/lib/python3.11/logging/__init__.py", line 1113, in emit
    stream.write(msg + self.terminator)
  File "/wo"""

CUT_SHORT_CHAINED = """\
Traceback (most recent call last):
  File "/work/main/learner/checkpoint.py", line 200, in save
    self._manager.save(step, args=args)
ValueError: RESOURCE_EXHAUSTED: Error writing "params.w/0": No space left on device [os_error_code='28']

The above exception was the direct cause of the following exception:

Traceback (most recent call last):
  File "/work/main/deploy/commands/services.py", line 190, in run_learner
    run_loop(service, LoopOptions(
  File "/work/main/deploy/run"""

INTERLEAVED = """\
Traceback (most recent call last):
  File "/work/main/actors/process.py", line 300, in cycle
14:02:11.123 WARNING impulse.follow: no weights for 10 s
    self._rollout()
  File "/work/main/actors/rollout.py", line 12, in _rollout
{"ts": "2026-01-01T00:00:00.000Z", "level": "INFO", "logger": "zenoh", "msg": "link closed"}
    raise ValueError("rollout failed")
ValueError: rollout failed
"""

GROUP = """\
  + Exception Group Traceback (most recent call last):
  |   File "/work/main/bus/session.py", line 3, in <module>
  |     run()
  | ExceptionGroup: two tasks failed (2 sub-exceptions)
  +-+---------------- 1 ----------------
    | Traceback (most recent call last):
    |   File "/work/main/bus/session.py", line 9, in task
    | ConnectionError: the router went away
    +------------------------------------
"""


def test_error_line_is_one_line_and_never_a_piece_of_a_traceback() -> None:
    assert error_line(CHAINED) == "RuntimeError: the event file could not be written"
    # Cut short by the full disk: the last thing said outside the traceback, never `File "/wo`.
    assert error_line(CUT_SHORT_AFTER_A_LOG_LINE) == ("ERROR   impulse.run: the metrics row of update 13: no space "
                                                      "left on device writing /run/x/metrics.jsonl")
    assert error_line(CUT_SHORT_CHAINED).startswith("ValueError: RESOURCE_EXHAUSTED"), "the cause, which is whole"
    assert error_line('Traceback (most recent call last):\n  File "/work/main/x.py", line 3, in <module>\n'
                      "    main()\n  File \"/wo") == CUT_SHORT
    assert error_line(INTERLEAVED) == "ValueError: rollout failed", "other threads' lines are passed over"
    assert error_line(GROUP) == "ExceptionGroup: two tasks failed (2 sub-exceptions)"
    long = "x" * 1000
    assert error_line(f"Traceback (most recent call last):\n  File \"a.py\"\nValueError: {long}\n") == \
        f"ValueError: {long}"[:MAX_ERROR_LINE - 3] + "..."
    assert error_line('{"ts": "2026-01-01T00:00:00.000Z", "level": "ERROR", "logger": "impulse.run", '
                      '"msg": "gone"}\n{"ts": "2026-01-01T00:00:01.000Z", "level": "INFO", "logger": "zenoh", '
                      '"msg": "closed"}\n') == "INFO zenoh: closed"
    for tail in (CHAINED, CUT_SHORT_AFTER_A_LOG_LINE, CUT_SHORT_CHAINED, INTERLEAVED, GROUP,
                 '  File "/x.py", line 1\n    ^^^^\n', "Traceback (most recent call last):\n"):
        line = error_line(tail)
        assert line is not None and "\n" not in line and not line[0].isspace(), (tail, line)
        assert not line.startswith(('File "', "Traceback", "^", "+-")), (tail, line)


def test_a_traceback_cut_short_on_a_full_disk_reads_as_the_full_disk(tmp_path: Path) -> None:
    log = tmp_path / "logs" / "learner.log"
    log.parent.mkdir()
    log.write_text('Traceback (most recent call last):\n  File "/work/main/deploy/runtime/runloop.py", line 3\n'
                   '  File "/wo')
    child = Child("learner", lambda restart: [], log)
    try:
        limit_writes(tmp_path, log.stat().st_size)  # the log filled the disk
        assert child.read_error_line() == \
            f"no space left on device writing {log} (0 B free of {log.stat().st_size} B)"
    finally:
        lift_write_limits()
    assert child.read_error_line() == CUT_SHORT, "with space left, it says what it saw"


PARENT = """
import sys, time
from pathlib import Path
import jax
jax.devices()  # JAX's backends up: from here on, its at-fork hook warns of a deadlock
from impulse.deploy.runtime.supervisor import Child, Supervisor
child = Child("sleeper", lambda restart: [sys.executable, "-c", "import time; time.sleep(60)"], Path(sys.argv[1]))
supervisor = Supervisor([child])
supervisor.start("sleeper")
print(child.pid, flush=True)
time.sleep(60)
"""


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] == "Z"  # a zombie no one has reaped yet
    except FileNotFoundError:
        return True


@pytest.mark.heavy
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_starts_without_the_fork_warning_and_dies_with_its_parent(tmp_path: Path) -> None:
    stderr = tmp_path / "parent.err"
    with stderr.open("w") as err:
        parent = subprocess.Popen([sys.executable, "-c", PARENT, str(tmp_path / "sleeper.log")],
                                  stdout=subprocess.PIPE, stderr=err, text=True)
    pid = None
    try:
        pid = int(parent.stdout.readline())
        deadline = time.monotonic() + 20
        while b"time.sleep(60)" not in Path(f"/proc/{pid}/cmdline").read_bytes():  # past the guard's exec
            assert time.monotonic() < deadline, "the child never ran its command"
            time.sleep(0.05)
        warned = stderr.read_text()
        assert "fork" not in warned, warned
        parent.kill()  # SIGKILL: nothing of the parent's runs
        parent.wait()
        deadline = time.monotonic() + 5
        while not _gone(pid):
            assert time.monotonic() < deadline, "the child outlived its parent"
            time.sleep(0.05)
    finally:
        parent.kill()
        parent.wait()
        if pid is not None and not _gone(pid):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.heavy
def test_a_child_whose_parent_is_not_the_one_named_stops_at_once() -> None:
    """The parent died between the fork and the child's request to die with it: the child's parent is then
    another process, and the child stops instead of running on as an orphan."""
    env = {**os.environ, PARENT_PID_ENV: str(os.getpid() + 100_000)}
    done = subprocess.run([sys.executable, "-c", GUARD, sys.executable, "-c", "print('ran')"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == -signal.SIGTERM and "ran" not in done.stdout
    env[PARENT_PID_ENV] = str(os.getpid())
    done = subprocess.run([sys.executable, "-c", GUARD, sys.executable, "-c",
                           f"import os; print('ran', os.environ.get({PARENT_PID_ENV!r}))"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout == "ran None\n", "the variable is not passed on to its children"


def _actor_status(incarnation: int) -> dict:
    return {"incarnation": incarnation, "steps_per_s": 1000.0, "policy_version": 3, "in_flight": 1, "levels": "x",
            "rejected": {}}


@pytest.mark.heavy
def test_a_restarted_child_shows_starting_until_its_own_first_status(tmp_path: Path) -> None:
    actor = Child("actor-0", lambda restart: [sys.executable, "-c", "import time; time.sleep(60)"],
                  tmp_path / "actor-0.log")
    supervisor = Supervisor([actor], give_up_after=3, backoff_s=(0.05,))
    supervisor.start(actor.name)
    try:
        statuses = {"actor-0": _actor_status(7)}
        [line] = render(statuses, [actor], parts_by_child([actor]), columns=300)
        assert f"pid {actor.pid} " in line and "1,000 steps/s" in line
        first = actor.pid
        statuses["actor-0"] = _actor_status(7)  # its last words, heard after the display's last redraw
        os.kill(first, signal.SIGKILL)
        deadline = time.monotonic() + 10
        while actor.pid in (None, first):
            assert time.monotonic() < deadline, "not restarted"
            for ended, _ in supervisor.exited():
                supervisor.restart_later(ended)
            supervisor.restart_due()
            time.sleep(0.01)
        [line] = render(statuses, [actor], parts_by_child([actor]), columns=300)
        assert f"pid {actor.pid} restarts 1 | starting for" in line, line
        statuses["actor-0"] = {**_actor_status(8), "steps_per_s": 2000.0}  # the new incarnation's first status
        [line] = render(statuses, [actor], parts_by_child([actor]), columns=300)
        assert f"pid {actor.pid} restarts 1 | 2,000 steps/s" in line, line
        # A status that says it comes from another process is never shown as this one's.
        statuses["actor-0"] = {**_actor_status(8), "pid": first}
        [line] = render(statuses, [actor], parts_by_child([actor]), columns=300)
        assert "starting for" in line, line
    finally:
        supervisor.stop([actor.name], 5)


def test_status_lines_show_the_alarms_and_the_evaluators_refusals():
    learner = {"policy_version": 7, "epoch": 1, "update": 7, "num_updates": 10, "skipped_non_finite": 3,
               "stale_streak": 25, "rejected": {}}
    line = status_display.learner_line(learner)
    assert line.startswith("v7 epoch 1 | SKIPPED 3 non-finite updates | last 25 batches ALL STALE | update 7/10")
    actor = {"policy_version": 4, "learners_seen": 2, "resyncs": 1, "rejected": {"foreign_learner": 5}}
    line = status_display.actor_line(actor, 0)
    assert "| 2 LEARNERS on the bus | re-synced 1x |" in line and "rejected 5" in line
    evaluator = {"policy_version": 9, "scored_version": 5, "mean": 0.5, "groups": {}, "seconds": 1.0,
                 "rejected": {"stale": 2, "digest": 1}}
    assert status_display.evaluator_line(evaluator).endswith("| rejected 3")
    assert status_display.alarms_part({"policy_version": 1, "stale_streak": 3, "learners_seen": 1}) == ""
