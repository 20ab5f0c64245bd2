"""`impulse curriculum serve|set|get|inspect|inject`: run the curriculum service, and talk to a live one.

`serve` runs the service process (`impulse launch` starts it with `--run RUN_DIR` when the run trains on random
levels). `inject LEVEL.json` sends a level file into the running service's buffer (it is checked there, at the
run's size). `set`, `get`, `inspect` and `inject` find a running service through the run directory's config (run
name and bus hub) and query it over the bus; they print what it answered and exit 1 if no service answered.
`inspect --checkpoint [STEP]` reads the level buffer from the run's checkpoints instead, with no service: a
finished or stopped run, distributed (the curriculum service's checkpoints) or fused (`impulse train` on random
levels).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import sys
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from typing import Any, TypeVar

from impulse.curriculum.client import CurriculumClient, CurriculumUnreachable
from impulse.deploy.commands.options import TOOL_RUN_HELP, add_run_and_connect
from impulse.deploy.config import ConfigError, apply_overrides, config_to_toml
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.run_dirs import open_run_for

log = logging.getLogger("impulse.curriculum")

CURRICULUM_SECTION = "curriculum."
CHECKPOINT_REST_S = 10.0
"""The curriculum service's checkpoints come at most this often (a crash loses at most this long of results)."""
Reply = TypeVar("Reply")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="curriculum_action", metavar="ACTION", required=True)
    serve = actions.add_parser("serve", help="run the curriculum service", allow_abbrev=False)
    add_run_and_connect(serve)
    serve.add_argument("--config", type=Path, metavar="FILE.toml", help="TOML config (without --run)")
    serve.add_argument("--resume", action="store_true", help="continue from the service's newest checkpoint")
    serve.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")

    set_ = actions.add_parser("set", help="change live knobs: KEY=VALUE ... (e.g. replay_prob=0.8)",
                              allow_abbrev=False)
    set_.add_argument("assignments", nargs="+", metavar="KEY=VALUE",
                      help="curriculum knobs, with or without the 'curriculum.' prefix")
    get = actions.add_parser("get", help="print the live knobs", allow_abbrev=False)
    inspect = actions.add_parser("inspect", help="print the level buffer", allow_abbrev=False)
    inspect.add_argument("--top", type=int, default=10, metavar="K", help="levels to list (default 10)")
    inspect.add_argument("--json", action="store_true", help="print the whole report as JSON")
    inspect.add_argument("--render", type=Path, metavar="DIR", help="draw the top K levels as PNG files in DIR")
    inspect.add_argument("--checkpoint", nargs="?", const=-1, type=int, metavar="STEP",
                         help="read the buffer from the run's checkpoint STEP (default: the newest) instead of "
                         "asking the live service")
    inject = actions.add_parser("inject", help="send a level file into the running curriculum's buffer",
                                allow_abbrev=False)
    inject.add_argument("level", type=Path, metavar="LEVEL.json", help="a Kinetix level file")
    for p in (set_, get, inspect, inject):
        add_run_and_connect(p, TOOL_RUN_HELP, required=True)


def run(args: argparse.Namespace, _config: object) -> int:
    if args.curriculum_action == "serve":
        return serve(args)
    opened = open_run_for("curriculum", None, run_dir=args.run, connect=args.connect)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened
    if args.curriculum_action == "inspect" and args.checkpoint is not None:
        return inspect_checkpoint(args, config, run_dir)
    if not config.uses_curriculum_service:
        print(f"impulse curriculum {args.curriculum_action}: run {config.name!r} has no curriculum service: it plays "
              f"the fixed level set env.levels={config.env.levels!r} (a curriculum runs with env.levels=random)",
              file=sys.stderr)
        return EXIT_USAGE
    if args.curriculum_action == "inspect":
        return inspect(args, config)
    if args.curriculum_action == "inject":
        return inject(args, config)
    assignments = None
    if args.curriculum_action == "set":
        assignments = [a[len(CURRICULUM_SECTION):] if a.startswith(CURRICULUM_SECTION) else a
                       for a in args.assignments]
    reply = _ask(config, args.curriculum_action, lambda client: client.knobs(assignments))
    if reply is None:
        return EXIT_FAILED
    if not reply.get("ok"):
        print(f"impulse curriculum {args.curriculum_action}: refused: {reply.get('error')}", file=sys.stderr)
        return EXIT_USAGE
    for name, (old, new) in reply.get("changed", {}).items():
        print(f"{name}: {old} -> {new}")
    if args.curriculum_action == "set" and not reply.get("changed"):
        print("nothing changed")
    if args.curriculum_action == "get":
        print(f"method = {reply.get('method')}")
        for name, value in reply["knobs"].items():
            print(f"{name} = {json.dumps(value)}")
    return 0


def inject(args: argparse.Namespace, config: RunConfig) -> int:
    """`inject LEVEL.json`: the file's JSON object to the service, which loads it at the run's size, checks it and
    puts it into its buffer; prints the slot, or the service's reason for refusing it."""
    try:
        document = json.loads(args.level.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        print(f"impulse curriculum inject: cannot read {args.level}: {err}", file=sys.stderr)
        return EXIT_USAGE
    reply = _ask(config, "inject", lambda client: client.inject(document))
    if reply is None:
        return EXIT_FAILED
    if not reply.get("ok"):
        print(f"impulse curriculum inject: refused: {reply.get('error')}", file=sys.stderr)
        return EXIT_USAGE
    print(f"{args.level.name}: level {reply['level_id']} in buffer slot {reply['slot']}"
          f"{' (in place of the lowest-scored level)' if reply.get('evicted') else ''}")
    return 0


def _ask(config: RunConfig, action: str, request: Callable[[CurriculumClient], Reply]) -> Reply | None:
    """`request` made of the run's curriculum service through an operator's client (`curriculum.client`); None,
    with the reason printed, when no readable answer came."""
    try:
        with CurriculumClient(config.bus, config.name, f"cli-{os.getpid()}") as client:
            return request(client)
    except CurriculumUnreachable as err:
        print(f"impulse curriculum {action}: {err}", file=sys.stderr)
        return None


def _show(args: argparse.Namespace, config: RunConfig, report: dict[str, Any], arrays: dict[str, Any]) -> None:
    if args.render:
        _render(config, arrays, report, args.render)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(format_report(report))


def inspect_checkpoint(args: argparse.Namespace, config: RunConfig, run_dir: Path) -> int:
    """`inspect --checkpoint [STEP]`: the report of the buffer a checkpoint holds (read only: a corrupt checkpoint
    is named, never moved)."""
    import jax

    from impulse.curriculum.methods import make_curriculum
    from impulse.curriculum.stats import inspect_report, top_levels
    from impulse.engine.env.spec import env_from_config
    from impulse.engine.pytree import tree_arrays
    from impulse.learner.checkpoint import CURRICULUM, Checkpointer, CheckpointError

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
    _show(args, config, report, arrays)
    return 0


def inspect(args: argparse.Namespace, config: RunConfig) -> int:
    reply = _ask(config, "inspect", lambda client: client.inspect(args.top, levels=bool(args.render)))
    if reply is None:
        return EXIT_FAILED
    if reply.error is not None:
        print(f"impulse curriculum inspect: refused: {reply.error}", file=sys.stderr)
        return EXIT_USAGE
    _show(args, config, reply.report, reply.arrays)
    return 0


def _render(config: RunConfig, arrays: dict, report: dict, out: Path) -> None:
    import jax
    import numpy as np

    from impulse.engine.env.spec import env_from_config
    from impulse.engine.levels.generator import sample_random_level
    from impulse.engine.pytree import tree_from_arrays
    from impulse.monitor.png import render_level, save_png

    spec, _ = env_from_config(config.env)
    template = jax.eval_shape(lambda key: sample_random_level(key, spec.sizes), jax.random.PRNGKey(0))  # no compile
    out.mkdir(parents=True, exist_ok=True)
    for i, row in enumerate(report["top"]):
        level = tree_from_arrays({k: np.asarray(v)[i] for k, v in arrays.items()}, template)
        path = out / f"{i:02d}-{row['level_id']:016x}.png"
        save_png(render_level(level), path)
        print(f"wrote {path}")


INTEGER_HISTOGRAMS = frozenset({"age", "replays"})
"""The inspect report's histograms of whole counts (`curriculum.stats.inspect_report`), shown with integer bins."""


def integer_bins(edges: list[float], counts: list[int]) -> list[tuple[str, int]] | None:
    """A histogram of whole numbers relabelled by the integers each bin holds ("0", "1", "2-3", ...), bins that
    hold no integer dropped; None when a bin that holds no integer has a count (the data are not whole numbers).

    The bins are numpy's (`numpy.histogram`: each half-open, the last one closed), so a whole number falls into
    the bin whose integers include it: the labels say exactly which values were counted."""
    rows = []
    for k, (lo, hi, count) in enumerate(zip(edges[:-1], edges[1:], counts, strict=True)):
        first = math.ceil(lo)
        last = math.floor(hi) if k == len(counts) - 1 else math.ceil(hi) - 1
        if first > last:
            if count:
                return None
            continue
        rows.append((str(first) if first == last else f"{first}-{last}", int(count)))
    return rows


def _bar(count: int, most: int, width: int = 30) -> str:
    return "#" * (round(width * count / most) if most else 0)


def format_report(report: dict[str, Any]) -> str:
    """The inspect report for a terminal: summary, histograms, top levels, lineage."""
    s = report["summary"]
    lines = [f"curriculum {report['method']}: {s.get('buffer_fill', 0):.0%} of {s['buffer_size']} slots filled, "
             f"{s.get('staged', 0)} candidates staged, policy version {report['policy_version']}"]
    for key in ("score_mean", "score_replay_weighted", "staleness_replay_weighted", "score_lag_mean", "learnable",
                "never_solved", "always_solved", "generation_mean", "shapes_mean", "joints_mean", "thrusters_mean"):
        if s.get(key) is not None and key in s:
            lines.append(f"  {key:<26} {s[key]:.3f}")
    lines.append("  turnover: " + ", ".join(f"{k[6:]} {v}" for k, v in s.items() if k.startswith("count_")))
    for name, hist in report["histograms"].items():
        if not hist["counts"]:
            continue
        lines.append(f"{name} histogram:")
        most = max(hist["counts"])
        whole = integer_bins(hist["edges"], hist["counts"]) if name in INTEGER_HISTOGRAMS else None
        if whole is not None:
            lines += [f"  {label:>9} {count:>5} {_bar(count, most)}" for label, count in whole]
            continue
        for lo, hi, count in zip(hist["edges"][:-1], hist["edges"][1:], hist["counts"], strict=True):
            lines.append(f"  {lo:>9.3g} .. {hi:<9.3g} {count:>5} {_bar(count, most)}")
    lines.append("top levels:")
    lines.append(f"  {'level id':<18} {'score':>8} {'solved':>7} {'eps':>6} {'age':>6} {'replays':>7} {'gen':>4}")
    for row in report["top"]:
        solved = "-" if row["solve_rate"] is None else f"{row['solve_rate']:.0%}"
        lines.append(f"  {row['level_id']:016x}   {row['score']:>8.4f} {solved:>7} {row['episodes']:>6.1f} "
                     f"{row['age']:>6} {row['replays']:>7} {row['generation']:>4}")
    if report["lineage"]:
        lines.append("lineage of mutated levels (child <- parent, generation):")
        for row in report["lineage"]:
            lines.append(f"  {row['level_id']:016x} <- {row['parent_id']:016x}  gen {row['generation']}")
    return "\n".join(lines)


def serve(args: argparse.Namespace) -> int:
    opened = open_run_for("curriculum serve", None, run_dir=args.run, toml=args.config, overrides=args.overrides,
                          connect=args.connect)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened
    from impulse.deploy.runtime.devices import restrict_gpus

    try:
        restrict_gpus(config.curriculum.devices)
    except ValueError as err:
        print(f"impulse curriculum serve: curriculum.devices: {err}", file=sys.stderr)
        return EXIT_USAGE
    from impulse.deploy.runtime.compile_cache import enable_compile_cache

    enable_compile_cache()
    from impulse.bus.roles import CURRICULUM_ROLE
    from impulse.bus.session import Bus
    from impulse.curriculum.methods import make_curriculum
    from impulse.curriculum.service import CURRICULUM_ID, CurriculumService
    from impulse.deploy.runtime.monitoring import CurriculumLogger, open_monitor
    from impulse.deploy.runtime.runloop import LoopOptions, run_loop
    from impulse.engine.env.spec import env_from_config
    from impulse.learner.checkpoint import CURRICULUM, Checkpointer, CheckpointError

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
            from impulse.learner.agent import make_agent
            from impulse.learner.candidate_scorer import PolicyScorer

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
