"""`impulse curriculum serve`, and what the curriculum's tools need JAX for: the service process, reading a level
buffer from a run's checkpoints (`inspect --checkpoint`) and drawing levels (`inspect --render`).

Apart from `deploy.commands.curriculum` (the live controls, which only talk to the service over the bus), so that
`impulse curriculum set` answers without loading JAX.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
from contextlib import nullcontext
from pathlib import Path

import jax
import numpy as np

from impulse.bus.roles import CURRICULUM_ROLE
from impulse.bus.session import Bus
from impulse.curriculum.methods import make_curriculum
from impulse.curriculum.service import CURRICULUM_ID, CurriculumService
from impulse.curriculum.stats import inspect_report, top_levels
from impulse.deploy.commands.curriculum import show_report
from impulse.deploy.config import ConfigError, apply_overrides, config_to_toml
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.compile_cache import enable_compile_cache
from impulse.deploy.runtime.devices import restrict_gpus
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.monitoring import CurriculumLogger, open_monitor
from impulse.deploy.runtime.run_dirs import open_run_for
from impulse.deploy.runtime.runloop import LoopOptions, run_loop
from impulse.engine.env.spec import env_from_config
from impulse.engine.levels.generator import sample_random_level
from impulse.engine.pytree import tree_arrays, tree_from_arrays
from impulse.learner.agent import make_agent
from impulse.learner.candidate_scorer import PolicyScorer
from impulse.learner.checkpoint import CURRICULUM, Checkpointer, CheckpointError
from impulse.monitor.png import render_level, save_png

log = logging.getLogger("impulse.curriculum")

CHECKPOINT_REST_S = 10.0
"""The curriculum service's checkpoints come at most this often (a crash loses at most this long of results)."""


def serve(args: argparse.Namespace) -> int:
    opened = open_run_for("curriculum serve", None, run_dir=args.run, toml=args.config, overrides=args.overrides,
                          connect=args.connect)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened

    try:
        restrict_gpus(config.curriculum.devices)
    except ValueError as err:
        print(f"impulse curriculum serve: curriculum.devices: {err}", file=sys.stderr)
        return EXIT_USAGE

    enable_compile_cache()

    spec, env_params = env_from_config(config.env)
    curriculum = make_curriculum(config.curriculum, spec, env_params, config.ppo.num_envs)
    checkpoint_dir = run_dir / "curriculum" / config.checkpoint.directory
    checkpoint_config = dataclasses.replace(config.checkpoint, keep_best=False)

    def resolve_knobs(current, assignments):
        try:
            return apply_overrides(current, assignments, source="live knob change")
        except ConfigError as err:
            raise ValueError(str(err)) from None

    with Checkpointer(checkpoint_dir, checkpoint_config) as checkpoints, \
            Bus(config.bus, config.name, CURRICULUM_ROLE.name, CURRICULUM_ID) as bus, \
            open_monitor(config) or nullcontext() as monitor:
        if args.resume and checkpoints.latest_step() is None and checkpoints.set_aside():
            log.warning("%s: the curriculum starts with an empty buffer", checkpoints.nothing_usable())
        scorer = None
        if curriculum.batch_scored:  # Kinetix's SFL: candidates are played by the learner's newest policy
            scorer = PolicyScorer(bus, make_agent(config.network, spec), env_params, config.curriculum.sfl_attempts)
        try:
            service = CurriculumService(curriculum, bus, checkpoints, config_to_toml(config), resolve_knobs,
                                        item=CURRICULUM, seed=config.seed, resume=args.resume,
                                        status_every_s=config.bus.status_every_s, scorer=scorer)
        except CheckpointError as err:
            print(f"impulse curriculum serve: cannot resume: {err}", file=sys.stderr)
            return EXIT_FAILED
        log.info("curriculum up: %s, buffer %d, batches of %d levels", curriculum.method,
                 config.curriculum.buffer_size, curriculum.batch_size)
        watcher = CurriculumLogger(monitor, service, config) if monitor is not None else None
        # Checkpoints count result messages applied (with checkpoint.every_updates = 0, after every one), at most
        # one per CHECKPOINT_REST_S: the messages come as often as the actors send, many times the learner's rate.
        run_loop(service, LoopOptions(checkpoint_every=max(config.checkpoint.every_updates, 1), idle_wait_s=0.002,
                                      min_seconds_between_saves=CHECKPOINT_REST_S,
                                      every_turn=watcher.poll if watcher is not None else None))
    log.info("curriculum stopped: %d samples served, %d result messages applied", service.samples,
             service.result_messages)
    if service.scoring_under_way:
        # Everything is checkpointed and closed; a thread still inside XLA would abort the interpreter's teardown
        # (SIGABRT), so the process ends here without one.
        log.info("leaving the candidate scoring under way unfinished")
        logging.shutdown()
        os._exit(0)
    return 0


def inspect_checkpoint(args: argparse.Namespace, config: RunConfig, run_dir: Path) -> int:
    """`inspect --checkpoint [STEP]`: the report of the buffer a checkpoint holds (read only: a corrupt checkpoint
    is named, never moved)."""

    if config.env.levels != "random":
        print(f"impulse curriculum inspect: run {config.name!r} plays the fixed level set "
              f"env.levels={config.env.levels!r}: it has no curriculum to inspect", file=sys.stderr)
        return EXIT_USAGE
    # A distributed run's curriculum service checkpoints beside the learner; a fused run keeps it in its own.
    service_dir = run_dir / "curriculum" / config.checkpoint.directory
    directory = service_dir if service_dir.is_dir() else run_dir / config.checkpoint.directory
    if not directory.is_dir():
        print(f"impulse curriculum inspect: {run_dir} holds no checkpoints yet ({directory} is missing)",
              file=sys.stderr)
        return EXIT_FAILED
    spec, env_params = env_from_config(config.env)
    curriculum = make_curriculum(config.curriculum, spec, env_params, config.ppo.num_envs)
    template = jax.eval_shape(curriculum.init, jax.random.PRNGKey(0))
    with Checkpointer(directory) as checkpoints:
        step = checkpoints.latest_step() if args.checkpoint < 0 else args.checkpoint
        if step is None:
            print(f"impulse curriculum inspect: no complete checkpoint in {directory}", file=sys.stderr)
            return EXIT_FAILED
        try:
            restored = checkpoints.restore({CURRICULUM: template}, step=step)
        except CheckpointError as err:
            print(f"impulse curriculum inspect: {err}", file=sys.stderr)
            return EXIT_FAILED
    state = restored.items[CURRICULUM]
    counters = restored.counters
    version = int(counters.get("policy_version", counters.get("update", 0)))
    report = inspect_report(state, spec.sizes, config.curriculum, version, args.top)
    report["checkpoint"] = {"directory": str(directory), "step": restored.step}
    arrays = tree_arrays(top_levels(state, spec.sizes, args.top)) if args.render else {}
    print(f"checkpoint {restored.step} of {directory}")
    show_report(args, config, report, arrays)
    return 0


def render_levels(config: RunConfig, arrays: dict, report: dict, out: Path) -> None:
    spec, _ = env_from_config(config.env)
    template = jax.eval_shape(lambda key: sample_random_level(key, spec.sizes), jax.random.PRNGKey(0))  # no compile
    out.mkdir(parents=True, exist_ok=True)
    for i, row in enumerate(report["top"]):
        level = tree_from_arrays({k: np.asarray(v)[i] for k, v in arrays.items()}, template)
        path = out / f"{i:02d}-{row['level_id']:016x}.png"
        save_png(render_level(level), path)
        print(f"wrote {path}")
