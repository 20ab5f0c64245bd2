"""`impulse learner` and `impulse actor`: one distributed service per process, driven by the shared run loop
(the curriculum service is `impulse curriculum serve`, in `deploy.commands.curriculum`).

`impulse launch` starts these as child processes on one machine (`--run RUN_DIR`, reading the config it wrote
there); they can also be started by hand, on one machine or several (`--connect ENDPOINT`).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable
from contextlib import nullcontext
from functools import partial
from pathlib import Path
from typing import Any

from impulse.actors.levels import CurriculumLevels, LevelSource, LocalLevels
from impulse.actors.process import Actor, actor_name
from impulse.bus.roles import ACTOR_ROLE, LEARNER_ROLE
from impulse.bus.session import Bus
from impulse.curriculum.wire import level_batch_template
from impulse.deploy.config import config_to_toml, write_resolved_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.compile_cache import enable_compile_cache
from impulse.deploy.runtime.devices import restrict_gpus
from impulse.deploy.runtime.exit_codes import EXIT_CANNOT_RUN, EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.monitoring import MetricsLogger, open_monitor, scalar_sinks_for
from impulse.deploy.runtime.run_dirs import create_run_dir, fine_tuning_for, open_run_for, remove_unstarted_run
from impulse.deploy.runtime.runloop import LoopOptions, run_loop
from impulse.engine.levels.sets import LevelSetError
from impulse.engine.memory import DoesNotFit
from impulse.learner.agent import env_and_agent
from impulse.learner.curriculum_inputs import batch_level_results
from impulse.learner.hosts import HostsError, join_hosts, local_copy
from impulse.learner.non_finite import NonFiniteUpdates
from impulse.learner.run import FINAL_EVALUATION, final_evaluation
from impulse.learner.service import LEARNER_ID, LearnerError, LearnerService
from impulse.monitor.scalars import ScalarSinkError

log = logging.getLogger("impulse.service")


def _resolve(args: argparse.Namespace, config: RunConfig, command: str) -> tuple[RunConfig, Path] | None:
    return open_run_for(command, config, run_dir=args.run, toml=getattr(args, "config", None),
                        overrides=args.overrides, connect=args.connect)


def run_learner(args: argparse.Namespace, config: RunConfig) -> int:
    fine_tuning = fine_tuning_for("learner", args.init_from, config)
    if fine_tuning is None:
        return EXIT_USAGE
    init_from, config = fine_tuning
    resolved = _resolve(args, config, "learner")
    if resolved is None:
        return EXIT_USAGE
    config, run_dir = resolved
    try:
        restrict_gpus(config.learner.devices)
    except ValueError as err:
        print(f"impulse learner: learner.devices: {err}", file=sys.stderr)
        return EXIT_USAGE

    try:
        sinks = scalar_sinks_for(config, run_dir)
    except ScalarSinkError as err:
        print(f"impulse learner: {err}", file=sys.stderr)
        return EXIT_USAGE
    enable_compile_cache()

    try:  # first: JAX must not have started a backend before the group is joined (imports start none)
        group = join_hosts(config.learner.hosts, config.learner.coordinator, args.host_index)
    except HostsError as err:
        print(f"impulse learner: {err}", file=sys.stderr)
        return EXIT_USAGE

    # A new run made here (not a launcher's, not resumed) is taken back if it is refused before it trains.
    created = create_run_dir(run_dir) and args.run is None and not args.resume and group.is_leader
    if args.run is None and group.is_leader:
        write_resolved_config(config, run_dir)
    spec, env_params, agent = env_and_agent(config.env, config.network)
    # The learner's other processes on several hosts write nothing of the run's: the leader does.
    leads = group.is_leader
    with Bus(config.bus, config.name, LEARNER_ROLE.name, group.name(LEARNER_ID), listen=args.hub) as bus, \
            (open_monitor(config) if leads else None) or nullcontext() as monitor:
        try:
            service = LearnerService(
                config.ppo, config.learner, config.checkpoint, seed=config.seed, num_updates=config.num_updates,
                batches_in_flight=config.actors.num_actors * config.actors.credits,
                status_every_s=config.bus.status_every_s, run_dir=run_dir, config_toml=config_to_toml(config),
                bus=bus, agent=agent, resume=args.resume, init_from=init_from,
                wire_compact=config.bus.wire_compact, group=group)
        except LearnerError as err:
            print(f"impulse learner: {err}", file=sys.stderr)
            _remove_refused_run(created, run_dir, config)
            return EXIT_FAILED
        log.info("learner up: run %s, epoch %d, policy version %d, %d of %d updates done", config.name,
                 service.epoch, service.version, service.update, service.num_updates)
        try:
            run_loop(service, LoopOptions(metrics_path=run_dir / "metrics.jsonl" if leads else None,
                                          checkpoint_every=config.checkpoint.every_updates,
                                          window_size=config.checkpoint.every_updates,
                                          should_stop=lambda: service.group_stopped,
                                          on_cycle=_learner_on_cycle(service, monitor),
                                          scalar_sinks=sinks if leads else None))
        except DoesNotFit as err:
            print(f"impulse learner: {err}", file=sys.stderr)
            _remove_refused_run(created, run_dir, config)
            return EXIT_CANNOT_RUN
        except NonFiniteUpdates as err:  # the same settings would fail the same way after a restart
            print(f"impulse learner: stopped: {err}", file=sys.stderr)
            return EXIT_CANNOT_RUN
        finished = service.finished()
        params = service.train.params
        if leads and finished and config.eval.attempts > 0:
            # Said before the learner leaves the bus (it evaluates after, so that the actors stop at once): the
            # launcher's display shows this phase, with its seconds so far, until the learner exits.
            service.report_phase(FINAL_EVALUATION)
    if not leads:
        log.info("learner process %d of %d %s at update %d of %d; the leader checkpoints", group.index, group.count,
                 "done" if finished else "stopped", service.update, service.num_updates)
    elif finished:
        final_evaluation(config, agent, env_params, local_copy(params), run_dir)
        log.info("learner done: %d updates, %s env steps", service.update, f"{service.env_steps:,}")
    elif service.update > service.updates_at_start:
        log.info("learner stopped at update %d of %d, checkpointed; --resume continues from there", service.update,
                 service.num_updates)
    else:
        log.info("learner stopped at update %d of %d before an update of its own: nothing new to checkpoint",
                 service.update, service.num_updates)
    return 0


def _remove_refused_run(created: bool, run_dir: Path, config: RunConfig) -> None:
    """After a refusal: remove the run directory this command made for a new run, unless it holds checkpoints."""
    if created and remove_unstarted_run(run_dir, run_dir / config.checkpoint.directory):
        print(f"impulse learner: removed {run_dir}, created for this run: nothing was trained", file=sys.stderr)


def _learner_on_cycle(service: Any, monitor: Any) -> Callable[[dict[str, Any], dict[str, float]], None]:
    """The learner notes the window for its status line; with a monitor, the metrics go to Rerun too."""

    def note(record: dict[str, Any], window: dict[str, float]) -> None:
        service.note_window(window)

    if monitor is None:
        return note
    return MetricsLogger(monitor, "learner", service.status, step_timeline="update", then=note)


def run_actor(args: argparse.Namespace, config: RunConfig) -> int:
    resolved = _resolve(args, config, "actor")
    if resolved is None:
        return EXIT_USAGE
    config, _ = resolved
    if config.actors.memory_fraction > 0:
        # Read by JAX's GPU backend when it starts, so it must be set before JAX first touches a device.
        os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", f"{config.actors.memory_fraction:g}")
    if config.actors.devices:
        try:
            restrict_gpus([config.actors.devices[args.index % len(config.actors.devices)]])
        except ValueError as err:
            print(f"impulse actor: actors.devices: {err}", file=sys.stderr)
            return EXIT_USAGE
    enable_compile_cache()

    spec, env_params, agent = env_and_agent(config.env, config.network)
    with Bus(config.bus, config.name, ACTOR_ROLE.name, actor_name(args.index)) as bus, \
            open_monitor(config) or nullcontext() as monitor:
        levels: LevelSource
        if config.uses_curriculum_service:
            template = level_batch_template(spec.sizes, config.ppo.num_envs)
            levels = CurriculumLevels(bus, template, config.curriculum.method)
        else:
            try:
                levels = LocalLevels(config.env, spec.sizes)
            except LevelSetError as err:
                print(f"impulse actor: env.levels: {err}", file=sys.stderr)
                return EXIT_FAILED
        actor = Actor(config.actors, num_envs=config.ppo.num_envs, num_steps=config.ppo.num_steps,
                      seed=config.seed, index=args.index, bus=bus, agent=agent, env_params=env_params,
                      levels=levels, level_results=partial(batch_level_results, agent, config.ppo),
                      env_steps_goal=config.total_env_steps // config.actors.num_actors, monitor=monitor,
                      monitor_config=config.monitor, restart_envs=config.ppo.restart_envs)
        log.info("%s up: %d envs x %d steps per batch, levels %s, incarnation %d", actor.name,
                 config.ppo.num_envs, config.ppo.num_steps, levels.description, actor.incarnation)
        on_cycle = MetricsLogger(monitor, actor.name, actor.status) if monitor is not None else None
        try:
            run_loop(actor, LoopOptions(on_cycle=on_cycle))
        except DoesNotFit as err:  # the launcher gives up on this exit status at once: no restart can fit
            print(f"impulse actor: {err}", file=sys.stderr)
            return EXIT_CANNOT_RUN
    return 0
