"""`impulse view RUN_DIR`: the Rerun viewer for a run, live.

It starts the Rerun server the run's processes stream to (the port of `monitor.url` in the run's config): the
native viewer when there is a display, else the web viewer, whose address it prints (on a remote machine, tunnel
both ports: `ssh -L 9090:localhost:9090 -L 9876:localhost:9876 HOST`). `--record FILE.rrd` also writes everything
the run streams to a file; with `--headless` there is no viewer, only the server writing that file (what `impulse
launch --record FILE.rrd` starts without `--view`). It runs until Ctrl-C; `impulse launch --view` starts it as one
of the run's processes.
The processes stream only while a viewer is up (see `monitor.stream`), so it can be started and stopped at any
time during a run.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import time

from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.run_dirs import open_run_for
from impulse.deploy.runtime.runloop import StopFlag
from impulse.deploy.runtime.supervisor import guarded
from impulse.monitor.stream import server_reachable
from impulse.monitor.viewer import viewer_plan

log = logging.getLogger("impulse.view")

SERVER_START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 10.0


def _stop(processes: list[subprocess.Popen[bytes]]) -> None:
    """Ctrl-C to each (the recorder finishes its file on it), then kill what is left after the timeout."""
    for process in reversed(processes):
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    deadline = time.monotonic() + STOP_TIMEOUT_S
    for process in processes:
        try:
            process.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def run_view(args: argparse.Namespace, config: RunConfig) -> int:
    opened = open_run_for("view", config, run_dir=args.run, overrides=args.overrides)
    if opened is None:
        return EXIT_USAGE
    config, _ = opened
    monitor = config.monitor
    if args.headless and args.record is None:
        print("impulse view: --headless only records: give it --record FILE.rrd", file=sys.stderr)
        return EXIT_USAGE
    if server_reachable(monitor.url):
        print(f"impulse view: something already listens on {monitor.url} (another viewer?); stop it, or choose "
              "another port with monitor.url=rerun+http://127.0.0.1:PORT/proxy for the whole run", file=sys.stderr)
        return EXIT_FAILED
    try:
        plan = viewer_plan(monitor.url, web=True if args.web else False if args.native else None,
                           web_port=monitor.web_port, bind=args.bind,
                           server_memory_limit=monitor.server_memory_limit,
                           viewer_memory_limit=monitor.viewer_memory_limit, record=args.record,
                           headless=args.headless)
    except (FileNotFoundError, ValueError) as err:
        print(f"impulse view: {err}", file=sys.stderr)
        return EXIT_FAILED
    logs = args.run / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    processes: list[subprocess.Popen[bytes]] = []
    with StopFlag("stopping the viewer") as stop, open(logs / "viewer.log", "ab") as output:
        try:
            for command in plan.commands:
                argv, env = guarded(command, dict(os.environ))  # dies with this process, no preexec_fn fork
                processes.append(subprocess.Popen(argv, stdout=output, stderr=subprocess.STDOUT, env=env))
                if len(processes) == 1 and not _wait_for_server(monitor.url, processes[0], stop):
                    print(f"impulse view: the Rerun server did not come up on {monitor.url}; see {output.name}",
                          file=sys.stderr)
                    return EXIT_FAILED
            if plan.headless:
                log.info("no viewer for run %s: a Rerun server at %s records everything streamed", config.name,
                         plan.address)
            elif plan.native:
                log.info("native Rerun viewer open for run %s, serving %s", config.name, plan.address)
            else:
                log.info("Rerun web viewer for run %s: open %s", config.name, plan.address)
            if args.record is not None:
                log.info("recording everything streamed to %s", args.record)
            while not stop.stop:
                ended = [p for p in processes if p.poll() is not None]
                if ended:
                    log.warning("a Rerun process ended (exit %s): %s; see %s", ended[0].returncode,
                                " ".join(ended[0].args[:2]), output.name)
                    return EXIT_FAILED
                time.sleep(0.2)
        finally:
            _stop(processes)
    return 0


def _wait_for_server(url: str, process: subprocess.Popen[bytes], stop: StopFlag) -> bool:
    deadline = time.monotonic() + SERVER_START_TIMEOUT_S
    while time.monotonic() < deadline and not stop.stop and process.poll() is None:
        if server_reachable(url):
            return True
        time.sleep(0.2)
    return False
