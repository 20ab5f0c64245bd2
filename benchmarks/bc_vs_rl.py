"""Behaviour cloning against the reinforcement learning that recorded its data: per level, a distributed run
(`impulse launch` of `configs/quick-launch.toml` on that level) trains with PPO while its recorder writes the
actors' episodes (`recorder.path`); then `impulse train-bc` clones a policy from the dataset's solved episodes,
and both policies are scored the same way (`eval.attempts` episodes from the level's start, sampled actions).

What it measures: how much of the RL policy's final skill a clone of its own experience recovers from the episodes
the run played while learning (most of them by earlier, weaker policies), at how many cloned steps. It does not
say how BC compares with RL at equal environment steps: the clone reuses the run's steps, it plays none.

Output: JSON lines on stdout (`record` = "config", one "level" per level), progress on stderr.

    impulse bench bc_vs_rl --levels handmade:s_easy_car_right handmade:s_easy_thrust_right
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from impulse.benchmarks._harness import REPO, emit, environment, progress

QUICK_LAUNCH = REPO / "configs" / "quick-launch.toml"
STEPS_PER_UPDATE = 64 * 64  # quick-launch's batch


def _run(command: list[str], log: Path, timeout_s: float) -> float:
    """Run `command` with its output in `log`; its wall time. Raises on failure, naming the log."""
    started = time.perf_counter()
    with log.open("wb") as out:
        done = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, timeout=timeout_s, cwd=REPO,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if done.returncode != 0:
        raise RuntimeError(f"{command[3]} failed ({done.returncode}); see {log}")
    return time.perf_counter() - started


def compare(level: str, args: argparse.Namespace, work: Path, port: int) -> dict[str, Any]:
    """One level: the RL run with its recorder, then the clone; both policies' scores and the dataset's sizes."""
    from impulse.learner.dataset import open_dataset

    name = level.rsplit(":", 1)[-1].rsplit("/", 1)[-1].removesuffix(".json")
    rl_dir, bc_dir = work / f"rl-{name}", work / f"bc-{name}"
    cli = [sys.executable, "-m", "impulse.deploy.cli"]
    rl_seconds = _run([*cli, "launch", "--config", str(QUICK_LAUNCH), f"env.levels={level}", f"eval.levels={level}",
                       f"seed={args.seed}", f"total_env_steps={args.updates * STEPS_PER_UPDATE}", f"run_dir={rl_dir}",
                       f"name=bcrl-{name}-{os.getpid()}", f"bus.hub=tcp/127.0.0.1:{port}",
                       f"eval.attempts={args.attempts}", "recorder.path={run_dir}/dataset", *args.overrides],
                      work / f"rl-{name}.log", args.timeout)
    rl_scores = json.loads((rl_dir / "eval.json").read_text())
    index = open_dataset(rl_dir / "dataset").index()
    bc_seconds = _run([*cli, "train-bc", "--dataset", str(rl_dir / "dataset"), f"run_dir={bc_dir}",
                       f"seed={args.seed}", f"eval.levels={level}", f"eval.attempts={args.attempts}",
                       f"bc.epochs={args.epochs}"], work / f"bc-{name}.log", args.timeout)
    bc_scores = json.loads((bc_dir / "eval.json").read_text())
    epochs = [json.loads(line) for line in (bc_dir / "metrics.jsonl").read_text().splitlines()]
    [rl] = rl_scores.values()
    [bc] = bc_scores.values()
    return {
        "record": "level", "level": level, "rl_updates": args.updates, "rl_env_steps": args.updates * STEPS_PER_UPDATE,
        "rl_solve_rate": rl["solve_rate"], "bc_solve_rate": bc["solve_rate"],
        "rl_return": rl["mean_return"], "bc_return": bc["mean_return"],
        "rl_length": rl["mean_length"], "bc_length": bc["mean_length"],
        "episodes_recorded": index.episodes, "steps_recorded": index.steps,
        "episodes_solved": int(index.solved.sum()), "steps_cloned": int(index.length[index.solved].sum()),
        "bc_held_out_loss": epochs[-1]["bc/held_out_loss"],
        "bc_held_out_agreement": epochs[-1]["bc/held_out_agreement"],
        "rl_seconds": round(rl_seconds, 1), "bc_seconds": round(bc_seconds, 1),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench bc_vs_rl", description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", nargs="+", required=True, help="levels as env.levels takes them")
    parser.add_argument("--updates", type=int, default=30, help="PPO updates of each RL run (default 30)")
    parser.add_argument("--epochs", type=int, default=20, help="cloning epochs (default 20)")
    parser.add_argument("--attempts", type=int, default=50, help="evaluation episodes per policy (default 50)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--port", type=int, default=7631, help="loopback port of the runs' bus hub")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds each run may take")
    parser.add_argument("--keep", type=Path, help="keep the run directories here (default: a temporary folder)")
    parser.add_argument("overrides", nargs="*", help="key=value overrides for the RL runs")
    args = parser.parse_args(argv)
    emit({"record": "config", "levels": args.levels, "updates": args.updates, "epochs": args.epochs,
          "attempts": args.attempts, "seed": args.seed, "overrides": args.overrides, **environment()})
    with tempfile.TemporaryDirectory(prefix="bc-vs-rl-") as scratch:
        work = args.keep or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        for level in args.levels:
            progress(f"{level}: RL run of {args.updates} updates with a recorder, then cloning ...")
            row = compare(level, args, work, args.port)
            progress(f"{level}: RL {row['rl_solve_rate']:.0%}, BC {row['bc_solve_rate']:.0%} "
                     f"({row['steps_cloned']:,} steps cloned)")
            emit(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
