"""`impulse evaluator`: the evaluator process alone (`learner.evaluator`), against a running run on this machine or
across machines (`--connect ENDPOINT`, with the evaluator's own credentials); `impulse launch` starts it with the
run when `evaluator.levels` is set. It needs no run directory of its own: give the run's config (`--config` and
the same overrides as the run, or `--run RUN_DIR` where the run directory is visible)."""

from __future__ import annotations

import argparse
import logging
import sys
from contextlib import nullcontext

from impulse.bus.session import Bus
from impulse.deploy.commands import EVALUATOR_ROLE
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.compile_cache import enable_compile_cache
from impulse.deploy.runtime.devices import restrict_gpus
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.monitoring import MetricsLogger, open_monitor
from impulse.deploy.runtime.run_dirs import open_run_for
from impulse.deploy.runtime.runloop import LoopOptions, run_loop
from impulse.engine.levels.sets import LevelSetError
from impulse.learner.agent import env_and_agent
from impulse.learner.evaluator import EVALUATOR_ID, EvaluatorService
from impulse.learner.scoring import load_level_sets

log = logging.getLogger("impulse.service")


def run_evaluator(args: argparse.Namespace, config: RunConfig) -> int:
    opened = open_run_for("evaluator", config, run_dir=args.run, toml=getattr(args, "config", None),
                          overrides=args.overrides, connect=args.connect)
    if opened is None:
        return EXIT_USAGE
    config, _ = opened
    if not config.evaluator.levels:
        print("impulse evaluator: evaluator.levels is empty: name the level sets to score on, e.g. "
              "evaluator.levels=kinetix:s,handmade", file=sys.stderr)
        return EXIT_USAGE
    try:
        restrict_gpus(config.evaluator.devices[:1])
    except ValueError as err:
        print(f"impulse evaluator: evaluator.devices: {err}", file=sys.stderr)
        return EXIT_USAGE
    enable_compile_cache()

    spec, env_params, agent = env_and_agent(config.env, config.network)
    try:
        sets = load_level_sets(config.evaluator.levels, spec.sizes)
    except LevelSetError as err:
        print(f"impulse evaluator: evaluator.levels: {err}", file=sys.stderr)
        return EXIT_FAILED
    with Bus(config.bus, config.name, EVALUATOR_ROLE.name, EVALUATOR_ID) as bus, \
            open_monitor(config) or nullcontext() as monitor:
        service = EvaluatorService(config.evaluator, seed=config.seed, status_every_s=config.bus.status_every_s,
                                   bus=bus, agent=agent, env_params=env_params, sets=sets)
        log.info("evaluator up: run %s, %d levels (%s), every %d policy versions, %d attempts each", config.name,
                 len(sets.names), config.evaluator.levels, config.evaluator.every_updates,
                 config.evaluator.attempts)
        on_cycle = MetricsLogger(monitor, EVALUATOR_ID, service.status) if monitor is not None else None
        run_loop(service, LoopOptions(on_cycle=on_cycle))
    return 0
