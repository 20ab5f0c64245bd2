"""`impulse launch`: a whole distributed run on this machine, as separate processes.

The launcher itself is the bus hub (a zenoh peer listening on `bus.hub`), so the learner and each actor can die
and come back without breaking the others' connections. It starts the learner, `actors.num_actors` actors
(`impulse learner --run RUN_DIR`, `impulse actor --run RUN_DIR --index N`) and, for runs on random levels, the
curriculum service (`impulse curriculum serve --run RUN_DIR --resume`), shows their status lines, restarts a
process that dies (the learner with `--resume`, from its newest checkpoint) after a back-off, and ends when the
learner has finished its run. `--init-from RUN_DIR` fine-tunes: the learner starts from that run's (or shipped
agent's) policy until it has checkpoints of its own. Ctrl-C (or SIGTERM) stops the actors first, then the
curriculum and the learner, which write final checkpoints; a second Ctrl-C kills everything at once.

Before it writes or starts anything, the launcher checks what every process will need (`deploy.runtime.preflight`: level
sets, the checkpoints a resume restores, credentials) and exits 1 with one error if something is wrong. A process
that fails the same way 3 times in a row at start-up is not restarted again (`deploy.runtime.supervisor`): if it is the
learner, the curriculum service or the last actor, the run is stopped in order and the launcher exits 1 naming
the process, its exit status and its error line; without some of its actors, the run goes on.

`--view` turns monitoring on for every process (`monitor.enabled`) and starts `impulse view RUN_DIR` first, so
the run streams its rollouts, curves and curriculum to a Rerun viewer from the start (`--record FILE.rrd` also
writes them to a file); the viewer is stopped last. `--record FILE.rrd` without `--view` does the same with no
viewer: `impulse view RUN_DIR --headless --record FILE.rrd`, a Rerun server that only writes the file.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time

from impulse.bus.codec import Rejected
from impulse.bus.inbox import Received
from impulse.bus.keys import OPERATOR, Keys
from impulse.bus.session import Bus
from impulse.bus.status import read_status
from impulse.deploy.config import write_resolved_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_CANNOT_RUN, EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.monitoring import viewer_config
from impulse.deploy.runtime.preflight import PreflightError, run_preflight
from impulse.deploy.runtime.process_roles import (
    LEARNER_ROLE,
    PROCESS_ROLES,
    Kind,
    LaunchPlan,
    ProcessRole,
    credential_roles,
    group,
    jax_processes,
    launch_children,
    launch_summary,
    needed_after_giving_up,
    parts_by_child,
    role_of,
    stop_stages,
)
from impulse.deploy.runtime.run_dirs import create_run_dir, fine_tuning_for, open_run_for, remove_unstarted_run
from impulse.deploy.runtime.runloop import StopFlag
from impulse.deploy.runtime.status_display import StatusDisplay, status_block
from impulse.deploy.runtime.supervisor import Child, Supervisor, describe_failure
from impulse.engine.memory import HOST_PROCESSES_ENV
from impulse.learner.run_directory import existing_run, holds_checkpoints
from impulse.learner.scoring import format_scores

log = logging.getLogger("impulse.launch")

POLL_S = 0.2


def run_launch(args: argparse.Namespace, config: RunConfig, roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> int:
    """The launch; `roles`: the registry of what it may start (`deploy.runtime.process_roles`)."""
    fine_tuning = fine_tuning_for("launch", args.init_from, config, resume=args.resume)
    if fine_tuning is None:
        return EXIT_USAGE
    init_from, config = fine_tuning
    opened = open_run_for("launch", config, run_dir=args.resume, overrides=args.overrides)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened
    if args.resume is None and holds_checkpoints(run_dir / config.checkpoint.directory):
        print(f"impulse launch: {existing_run(run_dir)}", file=sys.stderr)
        return EXIT_FAILED
    if config.learner.hosts > 1:
        print(f"impulse launch: learner.hosts={config.learner.hosts} is a learner on several machines, which "
              "`impulse launch` (one machine) does not start: start each learner process with `impulse learner "
              "--host-index N`, or use deploy/cluster/slurm/impulse.sbatch (docs/multi-host.md, \"A learner on "
              "several hosts\")", file=sys.stderr)
        return EXIT_USAGE
    expected_lag = config.actors.num_actors * config.actors.credits
    if expected_lag > config.ppo.max_policy_lag:
        log.warning("%d actors x %d credits can put batches %d policy versions behind the learner, more than "
                    "ppo.max_policy_lag=%d: a learner-bound run will drop batches as stale", config.actors.num_actors,
                    config.actors.credits, expected_lag, config.ppo.max_policy_lag)
    streams = args.view or args.record is not None  # the processes stream to a Rerun server `impulse view` starts
    if streams:
        config = viewer_config(config)
    plan = LaunchPlan(config, run_dir, resume=args.resume is not None, init_from=init_from, record=args.record,
                      view=args.view)
    try:  # before anything is written or started: a problem every process would hit is one error, not a crash loop
        run_preflight(config, run_dir, resume=args.resume is not None, credential_roles=credential_roles(plan, roles),
                      curriculum_service=config.uses_curriculum_service, cpu_only=True, init_from=init_from)
    except PreflightError as err:
        print(f"impulse launch: {err}", file=sys.stderr)
        return EXIT_FAILED
    created = create_run_dir(run_dir) and args.resume is None
    write_resolved_config(config, run_dir)

    children = launch_children(plan, roles)
    # On a CPU the processes that run batch-sized JAX programs share the host's memory.
    env = {**os.environ, "PYTHONUNBUFFERED": "1", HOST_PROCESSES_ENV: str(jax_processes(children, roles))}
    supervisor = Supervisor(children, env)
    display = StatusDisplay(log_every_s=args.status_every)
    parts = parts_by_child(children, roles)
    log.info("run %s in %s: %s; logs in %s", config.name, run_dir, ", ".join(launch_summary(plan, roles)),
             run_dir / "logs")
    # On a terminal the display is a table at the bottom of the screen with the log lines scrolling above it.
    with Bus(config.bus, config.name, OPERATOR, "launcher", listen=True) as bus, display:
        statuses_inbox = bus.inbox(bus.keys.status_pattern(), 256, drop_oldest=True)
        presence = bus.watch_alive(bus.keys.alive_pattern())
        statuses: dict[str, dict] = {}
        for child in children:
            supervisor.start(child.name)
        if streams and not args.view:
            log.info("recording what the processes stream to %s (no viewer; the Rerun server is %s)", args.record,
                     config.monitor.url)
        elif args.view:
            from impulse.monitor.viewer import has_display, web_viewer_address

            where = "the native viewer" if has_display() else web_viewer_address(config.monitor.url,
                                                                                  config.monitor.web_port)
            log.info("Rerun viewer: %s (the processes stream to %s)", where, config.monitor.url)
        finished = False
        failed: list[Child] = []  # given up on, and the run cannot go on without them
        with StopFlag("stopping the run: the actors first, then the curriculum and the learner") as stop:
            while not stop.stop:
                for received in statuses_inbox.poll():
                    _read_status(received, bus, statuses)
                for key, alive in presence.poll():
                    role, ident = bus.keys.parse_alive(key)
                    # Command-line tools and watchers come and go; a learner's instance token goes with its own.
                    if role != OPERATOR and Keys.instance_nonce(ident) is None:
                        log.info("%s %s the bus", ident, "joined" if alive else "left")
                for child, code in supervisor.exited():
                    role = role_of(child.name, roles)
                    if role is LEARNER_ROLE and code == 0:
                        finished = True
                        break
                    if code == 0 and role.ends_with_run:
                        log.info("%s ended: the learner finished the run", child.name)  # followers stop on their own
                        continue
                    if child.gave_up:
                        failed = give_up_on(child, children, roles)
                        if failed:
                            break
                        continue
                    delay = supervisor.restart_later(child)
                    log.warning("%s ended (%s); restarting it in %.0f s%s", child.name, describe_failure(child), delay,
                                role.restart_note)
                if failed:
                    log.error("stopping the run: %s", f"the {failed[0].name} gave up"
                              if role_of(failed[0].name, roles).kind is Kind.CRITICAL else "every actor gave up")
                    break
                if finished:
                    log.info("the learner finished the run; stopping the actors")
                    break
                supervisor.restart_due()
                if display.due():
                    display.show(status_block(statuses, children, parts))
                time.sleep(POLL_S)
            interrupted = stop.stop
            stopping: set[str] = set()

            def stop_children(names: list[str], timeout_s: float) -> None:
                """Stop `names`, showing them as stopping meanwhile (on a terminal)."""
                stopping.update(names)
                for received in statuses_inbox.poll():
                    _read_status(received, bus, statuses)
                display.redraw(status_block(statuses, children, parts, stopping=stopping))
                supervisor.stop(names, timeout_s)

            # In the registry's stop order: the actors and the evaluator first (they follow the learner), then the
            # recorder (it writes what they sent), the curriculum service and the learner (final checkpoints), and
            # the viewer last (the others' final metrics reach it).
            for lead, members in stop_stages(children, roles):
                running = [child.name for child in members if child.pid is not None]
                if not running:
                    continue
                if lead.stop_note:
                    log.info("%s", lead.stop_note)
                stop_children(running, lead.stop_timeout_s)
            display.show(status_block(statuses, children, parts))
    if failed:
        # A new run refused by what it needs (every process given up on said it cannot run with this
        # configuration) before it trained is taken back; the refusal, with the sizes to use, is on stderr.
        # (A learner that stopped on non-finite updates exits the same way, after writing metrics rows: kept.)
        metrics = run_dir / "metrics.jsonl"
        trained = metrics.is_file() and metrics.stat().st_size > 0
        refused = created and not trained and all(child.last_exit == EXIT_CANNOT_RUN for child in failed)
        removed = refused and remove_unstarted_run(run_dir, run_dir / config.checkpoint.directory)
        print(_failure_message(failed, logs_kept=not removed), file=sys.stderr)
        if removed:
            print(f"impulse launch: removed {run_dir}, created for this run: nothing was trained", file=sys.stderr)
        return EXIT_FAILED
    scores = run_dir / "eval.json"
    if finished and scores.is_file():
        log.info("evaluation of the final policy (%s):\n%s", scores, format_scores(json.loads(scores.read_text())))
    return 0 if finished or interrupted else EXIT_FAILED


def give_up_on(child: Child, children: list[Child], roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> list[Child]:
    """Say that the launcher gave up on `child`; returns the children without which the run cannot go on
    (`process_roles.needed_after_giving_up`: a critical role's process, or every actor once all have given up),
    or [] when it goes on without it."""
    if child.last_exit == EXIT_CANNOT_RUN:
        log.error("%s cannot run with this configuration (%s): not restarting it; its log: %s", child.name,
                  describe_failure(child), child.log_path)
    else:
        log.error("%s failed %d times in a row the same way (%s): not restarting it; its log: %s", child.name,
                  child.streak, describe_failure(child), child.log_path)
    needed = needed_after_giving_up(child, children, roles)
    if needed:
        return needed
    kind = role_of(child.name, roles).kind
    if kind is Kind.FOLLOWER:
        followers = group(children, Kind.FOLLOWER, roles)
        log.warning("the run goes on with %d of %d actors", sum(not f.gave_up for f in followers), len(followers))
    else:
        log.warning("the run goes on without the %s", child.name)
    return []


def _failure_message(failed: list[Child], logs_kept: bool = True) -> str:
    """The launcher's last words when it stopped a run because of `failed`: one line per distinct failure, naming
    the processes, the exit status, the error line and (`logs_kept`) the logs."""
    by_failure: dict[str, list[Child]] = {}
    for child in failed:
        by_failure.setdefault(describe_failure(child), []).append(child)
    lines = []
    for failure, children in by_failure.items():
        names = ", ".join(c.name for c in children[:-1]) + " and " * (len(children) > 1) + children[-1].name
        each = " each" if len(children) > 1 else ""
        logs = f"its log: {children[0].log_path}" if len(children) == 1 else \
            f"their logs are in {children[0].log_path.parent}"
        how = (" cannot run with this configuration" if children[0].last_exit == EXIT_CANNOT_RUN
               else f"{each} failed {children[0].streak} times in a row the same way")
        lines.append(f"impulse launch: stopped the run: {names}{how}: {failure}" + f" ({logs})" * logs_kept)
    return "\n".join(lines)


def _read_status(received: Received, bus: Bus, statuses: dict[str, dict]) -> None:
    """Keep the newest status of each process; a malformed one is counted and logged like any bad message."""

    try:
        heard = read_status(received, bus.keys)
    except Rejected as err:
        bus.rejects.record(err.reason, received.key, err.detail)
        return
    statuses[heard.ident] = heard.status
