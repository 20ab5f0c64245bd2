"""Fine-tuning a general agent against training from scratch (the Kinetix paper's second claim): on hand-made
levels the shipped agent does not solve zero-shot, `impulse train --init-from AGENT env.levels=LEVEL` and the same
run from a fresh network, for the same env-step budget and seeds, each scored on its level every `--eval-every`
updates (`eval.every_updates`, Kinetix's protocol: `--attempts` episodes from the level's start).

The network is the agent's (`--init-from` takes its [network] section; the scratch runs are given the same), and
so are the PPO settings unless `--set` changes them. Runs are real `impulse train` processes, one after the other.

Output: JSON lines on stdout (`record` = "config", one "run" per level x start x seed with its curve, one
"summary" per level x start: the final solve rates, the mean over the curve and the env steps each seed took to
reach SOLVED), progress on stderr, and a PNG (one panel per level, per-seed thin lines, means thick) at `--plot`.
`--from` trains nothing: it summarises and plots the "run" lines of earlier invocations, so seeds added later
join the first ones.

    impulse bench finetune --agent pretrained/general-s --levels kinetix:s/h2_one_wheel_car.json handmade:s_hop_over
    impulse bench finetune --agent pretrained/general-s --levels handmade:s_hop_over --env-steps 262144 --seeds 0
    impulse bench finetune --from first.jsonl more-seeds.jsonl --plot all.png
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from impulse.benchmarks._harness import LEVELS_DIR, REPO, emit, environment, progress
from impulse.benchmarks.learning import mean_and_error
from impulse.benchmarks.plot import Panel, Series, render

STARTS = ("pretrained", "scratch")
START_COLORS = {"pretrained": (44, 160, 44), "scratch": (127, 127, 127)}
COLUMN = "eval/mean"
SOLVED = 0.9
"""The solve rate at which a run counts as having learned its level (`env_steps_to_solved`)."""


def command(start: str, level: str, seed: int, run_dir: Path, agent: Path, network: list[str],
            args: argparse.Namespace) -> list[str]:
    settings = [f"env.levels={level}", f"eval.levels={level}", "curriculum=dr", f"seed={seed}",
                f"total_env_steps={args.env_steps}", f"run_dir={run_dir}",
                f"name={run_dir.name}", f"eval.every_updates={args.eval_every}", f"eval.attempts={args.attempts}",
                f"checkpoint.every_updates={args.eval_every}", *args.overrides]
    train = [sys.executable, "-m", "impulse.deploy.cli", "train", "--config", str(agent / "config.toml")]
    if start == "pretrained":
        return [*train, "--init-from", str(agent), *settings]
    return [*train, *network, *settings]


def network_overrides(agent: Path) -> list[str]:
    """The agent's [network] section as overrides, so the scratch runs train the same architecture."""
    from impulse.deploy.config import load_run_config
    from impulse.deploy.run_config import RunConfig

    network = load_run_config(RunConfig, agent).network
    return [f"network.{name}={json.dumps(value) if isinstance(value, bool) else value}"
            for name, value in vars(network).items()]


def curve(run_dir: Path, steps_per_update: int) -> list[dict[str, float]]:
    path = run_dir / "metrics.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
    return [{"env_steps": row["update"] * steps_per_update, "solve_rate": row[COLUMN]}
            for row in rows if COLUMN in row]


def train_one(start: str, level: str, seed: int, root: Path, agent: Path, network: list[str],
              args: argparse.Namespace, steps_per_update: int) -> dict[str, Any]:
    tag = f"{start}-{level.replace(':', '_').replace('/', '_')}-seed{seed}"
    run_dir, log_path = root / tag, root / f"{tag}.log"
    progress(f"[{tag}] training {args.env_steps:,} env steps; log: {log_path}")
    began = time.monotonic()
    with log_path.open("w") as log:
        returncode = subprocess.run(command(start, level, seed, run_dir, agent, network, args), cwd=REPO,
                                    stdout=log, stderr=subprocess.STDOUT,
                                    env={**os.environ, "IMPULSE_KINETIX_LEVELS": str(LEVELS_DIR)}).returncode
    points = curve(run_dir, steps_per_update)
    record = {"record": "run", "start": start, "level": level, "seed": seed, "returncode": returncode,
              "wall_s": round(time.monotonic() - began, 1), "curve": points,
              "final": points[-1]["solve_rate"] if points else math.nan}
    if returncode != 0:
        progress(f"[{tag}] exit {returncode}:\n{''.join(log_path.read_text().splitlines(True)[-15:])}")
    progress(f"[{tag}] final solve rate {record['final']:.2f}")
    return record


def env_steps_to(points: list[dict[str, float]], solve_rate: float) -> float | None:
    """The env steps of a run's first evaluation at or above `solve_rate`; None if it never got there."""
    return next((p["env_steps"] for p in points if p["solve_rate"] >= solve_rate), None)


def summarise(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One "summary" per level x start, in the order the runs came: the final solve rate and the mean over the
    whole curve (which rewards learning early and is less noisy than one last point), each as mean and standard
    error across seeds, and each seed's env steps to SOLVED."""
    summaries = []
    for level in dict.fromkeys(r["level"] for r in runs):
        for start in STARTS:
            mine = [r for r in runs if r["level"] == level and r["start"] == start]
            if not mine:
                continue
            finals = [r["final"] for r in mine]
            over_curve = [statistics.fmean(p["solve_rate"] for p in r["curve"]) for r in mine if r["curve"]]
            final_mean, final_se = mean_and_error(finals)
            curve_mean, curve_se = mean_and_error(over_curve)
            summaries.append({"record": "summary", "level": level, "start": start,
                              "seeds": [r["seed"] for r in mine], "finals": finals, "final_mean": final_mean,
                              "final_se": final_se, "curve_mean": curve_mean, "curve_se": curve_se,
                              "env_steps_to_solved": [env_steps_to(r["curve"], SOLVED) for r in mine]})
    return summaries


def read_runs(paths: list[Path]) -> list[dict[str, Any]]:
    """The "run" lines of earlier invocations' output."""
    runs = []
    for path in paths:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            try:
                record = json.loads(line) if line.strip() else {}
            except json.JSONDecodeError as err:
                raise SystemExit(f"{path}:{number}: not a JSON line ({err})") from None
            if record.get("record") == "run":
                runs.append(record)
    if not runs:
        raise SystemExit(f"no run lines in {', '.join(map(str, paths))}")
    return runs


def panel_title(level: str) -> str:
    """A level file's size folder and name (m/h0_unicycle.json), not the path it was given by; other values as they
    are."""
    path = Path(level)
    return f"{path.parent.name}/{path.name}" if path.suffix == ".json" and path.parent.name else level


def plot(runs: list[dict[str, Any]], levels: list[str], path: Path) -> None:
    panels = []
    for level in levels:
        series = []
        for start in STARTS:
            mine = [r for r in runs if r["level"] == level and r["start"] == start and r["curve"]]
            for r in mine:
                series.append(Series(f"{start}, one seed", [p["env_steps"] / 1e6 for p in r["curve"]],
                                     [p["solve_rate"] for p in r["curve"]], START_COLORS[start], width=1,
                                     dashed=True, markers=False))
            if mine:
                length = min(len(r["curve"]) for r in mine)
                xs = [p["env_steps"] / 1e6 for p in mine[0]["curve"][:length]]
                ys = [statistics.fmean(r["curve"][i]["solve_rate"] for r in mine) for i in range(length)]
                series.append(Series(f"{start}, mean of {len(mine)} seeds", xs, ys, START_COLORS[start]))
        panels.append(Panel(panel_title(level), series, "env steps (millions)", "solve rate", (0.0, 1.0)))
    render(panels, path, "Fine-tuning the general agent vs training from scratch")
    progress(f"plot: {path}")


def train_all(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Every level x seed x start, one `impulse train` after the other, each "run" line emitted as it ends."""
    if not (args.agent / "config.toml").is_file():
        raise SystemExit(f"{args.agent} holds no config.toml: --agent takes a run directory")
    from impulse.deploy.config import load_run_config
    from impulse.deploy.run_config import RunConfig

    network = network_overrides(args.agent)
    config = load_run_config(RunConfig, args.agent, args.overrides)
    steps_per_update = config.ppo.num_envs * config.ppo.num_steps
    emit({"record": "config", **environment(), "agent": str(args.agent), "levels": args.levels,
          "seeds": args.seeds, "env_steps": args.env_steps, "eval_every": args.eval_every,
          "attempts": args.attempts, "overrides": args.overrides, "steps_per_update": steps_per_update})
    root = args.keep or Path(tempfile.mkdtemp(prefix="impulse-finetune-"))
    root.mkdir(parents=True, exist_ok=True)
    runs: list[dict[str, Any]] = []
    try:
        for level in args.levels:
            for seed in args.seeds:
                for start in STARTS:
                    record = train_one(start, level, seed, root, args.agent, network, args, steps_per_update)
                    emit(record)
                    runs.append(record)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    return runs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench finetune", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agent", type=Path, default=REPO / "pretrained" / "general-s",
                        help="the agent to fine-tune (a run directory; default pretrained/general-s)")
    parser.add_argument("--levels", nargs="+", help="one env.levels value per task")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--env-steps", type=int, default=64 * 8192, help="env-step budget per run")
    parser.add_argument("--eval-every", type=int, default=8, help="updates between evaluation points")
    parser.add_argument("--attempts", type=int, default=20)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--keep", type=Path, help="keep run directories and logs here (default: a temp dir)")
    parser.add_argument("--from", dest="earlier", nargs="+", type=Path, metavar="JSONL",
                        help="train nothing: summarise (and --plot) the runs in these earlier outputs")
    args = parser.parse_args(argv)
    if args.earlier:
        runs = read_runs(args.earlier)
    elif not args.levels:
        parser.error("--levels is required (or --from, to summarise earlier runs)")
    else:
        runs = train_all(args)
    for summary in summarise(runs):
        emit(summary)
        progress(json.dumps(summary))
    if args.plot is not None:
        plot(runs, list(dict.fromkeys(r["level"] for r in runs)), args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
