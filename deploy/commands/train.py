"""`impulse train` and `impulse eval`: the fused run (`learner.run.FusedRun`) driven by the shared run loop, and
evaluation of a checkpoint.

Neither is ever silent for long: `impulse train` shows what it builds and compiles before the first update (a
heartbeat: `deploy.runtime.progress.Heartbeat`), then its progress row (`ProgressLine`: phase, update n/N, steps/s,
ETA, solve rate, skipped non-finite updates), then its final evaluation; `impulse eval` shows each phase (loading,
compiling and playing the evaluation, recording, writing a video) with its seconds, from its first second on. On a
terminal these are live displays below the log lines; otherwise log lines every few seconds.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from impulse.deploy.config import (
    ConfigError,
    config_to_toml,
    resolve_config,
    write_resolved_config,
)
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.compile_cache import enable_compile_cache
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.monitoring import scalar_sinks_for
from impulse.deploy.runtime.progress import Heartbeat, ProgressLine
from impulse.deploy.runtime.run_dirs import (
    create_run_dir,
    fine_tuning_for,
    locate_checkpoint,
    open_run_for,
    remove_unstarted_run,
)
from impulse.deploy.runtime.runloop import LoopOptions, run_loop
from impulse.learner.non_finite import NonFiniteUpdates
from impulse.learner.run import FusedRun, RunError, evaluate_run, export_policy
from impulse.learner.scoring import format_scores
from impulse.monitor.scalars import ScalarSinkError, check_sinks
from impulse.monitor.video import check_video_path, write_episodes_video

log = logging.getLogger("impulse.train")


@dataclass
class RunSummary:
    updates: int
    env_steps: int
    compile_s: float
    steps_per_s: float
    """Env steps per second of this process's training (rollout and update, after compiling)."""
    final_metrics: dict[str, float]
    eval_scores: dict[str, dict[str, float]] | None


def train_run(
    config: RunConfig,
    run_dir: Path,
    config_toml: str,
    resume: bool = False,
    stop_after_updates: int | None = None,
    init_from: Path | None = None,
) -> RunSummary:
    """Train until `config.total_env_steps` (or `stop_after_updates` more updates, for tests and benchmarks),
    checkpointing on the configured cadence and when stopped, then evaluate if the run is complete. `init_from`: a
    run directory whose newest policy the new run starts from (fine-tuning)."""

    sinks = scalar_sinks_for(config, run_dir)
    with Heartbeat("building the environment and the network", logger=log) as beat:
        run = FusedRun(config, run_dir, config_toml, resume=resume, stop_after_updates=stop_after_updates,
                       init_from=init_from, on_phase=beat.phase)
    progress = ProgressLine(run.progress().total_env_steps, num_updates=run.trainer.num_updates)
    run.on_phase = progress.phase  # its periodic evaluations
    loop = run_loop(run, LoopOptions(metrics_path=run_dir / "metrics.jsonl",
                                     checkpoint_every=config.checkpoint.every_updates,
                                     window_size=config.checkpoint.every_updates, scalar_sinks=sinks,
                                     progress=progress))
    with Heartbeat(logger=log) as beat:  # shown once the final evaluation starts, if there is one
        scores = run.evaluate_at_end(on_phase=beat.phase)
    return RunSummary(
        updates=run.update,
        env_steps=run.env_steps,
        compile_s=run.compile_s,
        steps_per_s=loop.steps_per_s,
        final_metrics=loop.last,
        eval_scores=scores,
    )


def run_train(args: argparse.Namespace, config: RunConfig) -> int:
    try:
        check_sinks(config.monitor)
    except ScalarSinkError as err:
        print(f"impulse train: {err}", file=sys.stderr)
        return EXIT_USAGE
    enable_compile_cache()
    fine_tuning = fine_tuning_for("train", args.init_from, config, resume=args.resume)
    if fine_tuning is None:
        return EXIT_USAGE
    init_from, config = fine_tuning
    opened = open_run_for("train", config, run_dir=args.resume, overrides=args.overrides)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened
    created = create_run_dir(run_dir) and args.resume is None
    write_resolved_config(config, run_dir)
    log.info("run directory %s", run_dir)
    try:
        summary = train_run(config, run_dir, config_to_toml(config), resume=args.resume is not None,
                            stop_after_updates=args.updates, init_from=init_from)
    except RunError as err:
        print(f"impulse train: {err}", file=sys.stderr)
        if created and remove_unstarted_run(run_dir, run_dir / config.checkpoint.directory):
            print(f"impulse train: removed {run_dir}, created for this run: nothing was trained", file=sys.stderr)
        return EXIT_FAILED
    except NonFiniteUpdates as err:
        print(f"impulse train: stopped: {err}", file=sys.stderr)
        return EXIT_FAILED
    log.info(
        "done: %d updates, %s env steps, %.0f env steps/s (rollout and update, after compiling), compile %.1f s",
        summary.updates, f"{summary.env_steps:,}", summary.steps_per_s, summary.compile_s,
    )
    return 0


EVAL_SECONDS_PER_STEP = 1 / 30
"""Evaluation episodes are recorded as if played at 30 agent steps per second of `wall` time."""


def _open_checkpoint(args: argparse.Namespace, command: str) -> tuple[RunConfig, Path, int | None] | None:
    """(config, run directory, checkpoint step or None for the newest) of `--checkpoint`, with the key=value
    overrides; None after printing the problem as `impulse COMMAND: ...`."""
    try:
        run_dir, step = locate_checkpoint(args.checkpoint)
        config = resolve_config(RunConfig, run_dir / "config.toml", args.overrides)
    except (FileNotFoundError, ConfigError) as err:
        print(f"impulse {command}: {err}", file=sys.stderr)
        return None
    return config, run_dir, step


def run_eval(args: argparse.Namespace, config: RunConfig) -> int:
    opened = _open_checkpoint(args, "eval")
    if opened is None:
        return EXIT_USAGE
    config, run_dir, step = opened
    if args.video is not None:
        try:
            check_video_path(args.video)
        except ValueError as err:
            print(f"impulse eval: --video: {err}", file=sys.stderr)
            return EXIT_USAGE
    recorders = ([("the recording", args.record, _recorder(config.name, args.record))] if args.record is not None
                 else []) + ([("the video", args.video, _video_writer(args.video))] if args.video is not None else [])
    # From here on: compiling the evaluation takes tens of seconds on a busy CPU.
    with Heartbeat("loading the checkpoint's configuration and the levels", logger=log) as beat:
        enable_compile_cache()

        def write(names: list[str], episodes: Any, policy_version: int) -> None:
            for what, path, writer in recorders:
                phase = f"writing {what} {path} ({len(names)} levels, {episodes.first.shape[0]} frames each)"
                log.info("%s ...", phase)
                beat.phase(phase)
                writer(names, episodes, policy_version)

        def scored(done: int, total: int, name: str, solve_rate: float) -> None:
            rates.append(solve_rate)
            beat.phase(f"scored {done}/{total} levels, mean solve rate {sum(rates) / len(rates):.0%}")

        rates: list[float] = []
        try:
            table = evaluate_run(config, run_dir, step=step, levels=args.levels, attempts=args.attempts,
                                 seed=args.seed, greedy=args.greedy, recorder=write if recorders else None,
                                 on_phase=beat.phase, on_level=scored)
        except RunError as err:
            print(f"impulse eval: {err}", file=sys.stderr)
            return EXIT_FAILED

    print(format_scores(table))
    if args.record is not None:
        print(f"recorded one episode per level in {args.record} (open it with `rerun {args.record}`)")
    if args.video is not None:
        print(f"wrote one episode per level to {args.video}")
    if args.json is not None:
        args.json.write_text(json.dumps(table, indent=2))
    return 0


def _recorder(run: str, path: Path) -> Callable[[list[str], Any, int], None]:
    """Writes evaluation episodes to an .rrd file, under rollouts/eval/<level name>."""

    def record(names: list[str], episodes: Any, policy_version: int) -> None:
        # Rerun loads only when a recording is asked for: a machine without rerun-sdk evaluates too (docs/gpu.md).
        from impulse.monitor.blueprint import episodes_blueprint
        from impulse.monitor.rollouts import RolloutFrames, log_rollout
        from impulse.monitor.stream import open_recording

        entity_names = tuple(re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(name).stem or name) for name in names)
        steps, first = episodes.steps, episodes.first
        frames = RolloutFrames(
            source="eval", states=episodes.watched.state, actuation=episodes.watched.actuation,
            reward=np.asarray(steps.reward), done=np.asarray(steps.done), solved=np.asarray(steps.solved),
            truncated=np.asarray(steps.truncated), episode_return=np.asarray(steps.episode_return),
            policy_version=policy_version, first_step=0, episodes_before=np.zeros(len(names), np.int64),
            started_at=time.time(), seconds=first.shape[0] * EVAL_SECONDS_PER_STEP, names=entity_names, keep=first)
        recording = open_recording(run, path=path, blueprint=episodes_blueprint("eval", entity_names))
        log_rollout(recording, frames)
        recording.flush()
        recording.disconnect()

    return record


def _video_writer(path: Path) -> Callable[[list[str], Any, int], None]:
    """Writes evaluation episodes side by side as an animated GIF or WebP, or an MP4 (`monitor.video`)."""

    def write(names: list[str], episodes: Any, policy_version: int) -> None:
        write_episodes_video(path, names, episodes, fps=1 / EVAL_SECONDS_PER_STEP)

    return write


def run_export(args: argparse.Namespace, config: RunConfig) -> int:
    """`impulse export`: a run's policy alone, in a directory small enough to ship (see `export_policy`)."""

    enable_compile_cache()
    opened = _open_checkpoint(args, "export")
    if opened is None:
        return EXIT_USAGE
    config, run_dir, step = opened
    note = {}
    for item in args.note:
        key, sep, value = item.partition("=")
        if not sep or not key:
            print(f"impulse export: --note takes KEY=VALUE, got {item!r}", file=sys.stderr)
            return EXIT_USAGE
        note[key] = value
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        counters = export_policy(config, run_dir, args.out, config_to_toml(config), step=step, note=note)
    except RunError as err:
        print(f"impulse export: {err}", file=sys.stderr)
        return EXIT_FAILED
    write_resolved_config(config, args.out)
    (args.out / "agent.json").write_text(json.dumps({"source": str(run_dir), **counters}, indent=2) + "\n")
    size = sum(f.stat().st_size for f in args.out.rglob("*") if f.is_file())
    print(f"exported the policy of {run_dir} (update {counters.get('update')}, "
          f"{counters.get('env_steps', 0):,} env steps) to {args.out}: {size / 1e6:.1f} MB")
    return 0
