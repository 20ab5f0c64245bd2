"""`impulse curriculum serve|set|get|inspect|inject`: run the curriculum service, and talk to a live one.

What needs JAX (serving, `inspect --checkpoint`, `--render`) is in `deploy.commands.curriculum_service`, loaded for
those actions only, so that the live controls answer at once.

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
import json
import logging
import math
import os
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any, TypeVar

from impulse.curriculum.client import CurriculumClient, CurriculumUnreachable
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.run_dirs import open_run_for

log = logging.getLogger("impulse.curriculum")

CURRICULUM_SECTION = "curriculum."
Reply = TypeVar("Reply")


def run(args: argparse.Namespace, _config: object) -> int:
    if args.curriculum_action == "serve":
        return _jax_side().serve(args)
    opened = open_run_for("curriculum", None, run_dir=args.run, connect=args.connect)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened
    if args.curriculum_action == "inspect" and args.checkpoint is not None:
        return _jax_side().inspect_checkpoint(args, config, run_dir)
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


def _jax_side() -> ModuleType:
    """`deploy.commands.curriculum_service`, imported when an action needs JAX (serving, reading a checkpoint,
    drawing levels): the live controls answer without loading it."""
    from impulse.deploy.commands import curriculum_service

    return curriculum_service


def show_report(args: argparse.Namespace, config: RunConfig, report: dict[str, Any], arrays: dict[str, Any]) -> None:
    """Print an inspect report (a table, or JSON with --json), drawing its top levels first with --render."""
    if args.render:
        _jax_side().render_levels(config, arrays, report, args.render)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(format_report(report))


def inspect(args: argparse.Namespace, config: RunConfig) -> int:
    reply = _ask(config, "inspect", lambda client: client.inspect(args.top, levels=bool(args.render)))
    if reply is None:
        return EXIT_FAILED
    if reply.error is not None:
        print(f"impulse curriculum inspect: refused: {reply.error}", file=sys.stderr)
        return EXIT_USAGE
    show_report(args, config, reply.report, reply.arrays)
    return 0


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


