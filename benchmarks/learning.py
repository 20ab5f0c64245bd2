"""Distributed against fused on the task that matters: the same agent trained on random S levels with a curriculum
by `impulse train` (one process) and by `impulse launch` (learner, curriculum service, two actors and the
evaluator, with real policy lag), for the same env-step budget and seeds, scored zero-shot on Kinetix's S levels
and our hand-made S levels while it trains and at the end.

What each mode runs (real processes, one after the other, so they never share the machine):
- fused: `impulse train`, evaluating every `--eval-every` updates through `eval.every_updates`;
- distributed: `impulse launch` with `actors.num_actors` actors and the evaluator (`evaluator.every_updates`; it
  scores the newest policy and may skip versions while it works, so its points can be fewer).
Both score with `learner.scoring.score_policy` (Kinetix's protocol: `--attempts` episodes per level from its
start, stochastic policy) under the key `seed + 1 + policy version`, so a point of either mode at the same version
is scored the same way. A point's env steps are its policy version x the steps of one update.

At the end every run's newest checkpoint is scored once more in this process (`learner.run.evaluate_run`, the
function `impulse eval` uses) with one evaluation seed for all runs: that is the final zero-shot table. The bar
it checks: the distributed mode's mean final Kinetix-S solve rate is at least 90% of the fused mode's, or the
two means are within two standard errors (of the difference, across seeds).

Output: JSON lines on stdout (`record` = "config", "run" with the curve, the final scores, wall time, policy lag
and drops, then one "summary" per mode and one "bar"), progress on stderr, and a PNG of the curves (per seed thin,
mean thick) at `--plot`.

    impulse bench learning                                   # CPU: 3 seeds x 2 modes, small network, 0.5M steps
    impulse bench learning --seeds 0 --env-steps 131072      # a quick look
    impulse bench learning --curriculum plr --set ppo.learning_rate=1e-4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from impulse.benchmarks._harness import LEVELS_DIR, REPO, emit, environment, progress
from impulse.benchmarks.plot import Panel, Series, render

MODES = ("fused", "distributed")
EVAL_SETS = "kinetix:s,handmade"
KINETIX_S = "kinetix:s"
HANDMADE = "handmade"
SET_TITLES = {KINETIX_S: "Kinetix S levels (zero-shot)", HANDMADE: "our hand-made S levels (zero-shot)"}
MODE_COLORS = {"fused": (31, 119, 180), "distributed": (214, 39, 40)}
FINAL_EVAL_SEED = 12345
"""The evaluation seed of every run's final scoring, so all runs meet the same episode keys."""

QUICK = [
    "env.size=s", "env.levels=random",
    "network.kind=entity", "network.width=64", "network.depth=2",
    "ppo.num_envs=64", "ppo.num_steps=64", "ppo.num_minibatches=4", "ppo.update_epochs=4",
    "ppo.learning_rate=3e-4", "ppo.anneal_lr=false",
    "checkpoint.every_updates=32",
]
"""The curriculum benchmark's CPU settings (benchmarks/RESULTS.md, "Curriculum"): 4,096 env steps per update."""


@dataclass(frozen=True)
class Settings:
    modes: tuple[str, ...]
    seeds: tuple[int, ...]
    curriculum: str
    env_steps: int
    eval_every: int
    attempts: int
    actors: int
    overrides: tuple[str, ...]
    timeout_s: float

    def common(self, seed: int, run_dir: Path) -> list[str]:
        return [*QUICK, f"curriculum={self.curriculum}", f"seed={seed}", f"total_env_steps={self.env_steps}",
                f"run_dir={run_dir}", f"name={run_dir.name}", *self.overrides]


def update_steps(overrides: tuple[str, ...]) -> int:
    """Env steps of one update of every run: QUICK's sizes, or the overrides' (a GPU run sets its own)."""
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig

    return resolve_config(RunConfig, None, [*QUICK, *overrides]).ppo.steps_per_update


def command(mode: str, seed: int, run_dir: Path, settings: Settings) -> list[str]:
    """The command line of one run."""
    cli = [sys.executable, "-m", "impulse.deploy.cli"]
    common = settings.common(seed, run_dir)
    if mode == "fused":
        return [*cli, "train", *common, f"eval.levels={EVAL_SETS}", f"eval.every_updates={settings.eval_every}",
                f"eval.attempts={settings.attempts}"]
    return [*cli, "launch", *common, f"actors.num_actors={settings.actors}", f"evaluator.levels={EVAL_SETS}",
            f"evaluator.every_updates={settings.eval_every}", f"evaluator.attempts={settings.attempts}",
            "eval.attempts=0"]


def metrics_rows(run_dir: Path) -> list[dict[str, Any]]:
    path = run_dir / "metrics.jsonl"
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def curve(rows: list[dict[str, Any]], steps_per_update: int) -> list[dict[str, float]]:
    """The evaluation points of a run: env steps of the policy scored, and the solve rate per set."""
    points = []
    for row in rows:
        if "eval/policy_version" not in row:
            continue
        points.append({"env_steps": row["eval/policy_version"] * steps_per_update,
                       "time_s": row["time_s"] - rows[0]["time_s"],
                       KINETIX_S: row.get(f"eval/{KINETIX_S}", math.nan),
                       HANDMADE: row.get(f"eval/{HANDMADE}", math.nan)})
    return points


HEALTH_WINDOW = 16
"""Updates at the start and at the end of a run over which its policy entropy is averaged."""


def run_health(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Policy lag and drops as the learner wrote them (the distributed mode's; the fused mode has none), and how
    the updates went: mean clip fraction and KL (from the clip's centre), and the policy entropy over the first
    and the last HEALTH_WINDOW updates (a policy that learns becomes less random)."""
    lags = [row["policy_lag"] for row in rows if "policy_lag" in row]
    last = rows[-1] if rows else {}
    drops = {k.removeprefix("drops/"): v for k, v in last.items() if k.startswith("drops/") and v}

    def mean_of(column: str, part: list[dict[str, Any]]) -> float | None:
        values = [row[column] for row in part if row.get(column) is not None]
        return float(np.mean(values)) if values else None

    return {"updates": int(last.get("update", 0)), "env_steps": int(last.get("env_steps", 0)),
            "policy_lag_mean": float(np.mean(lags)) if lags else None,
            "policy_lag_max": int(max(lags)) if lags else None,
            "drops": drops, "batches_dropped": int(sum(drops.values())),
            "clip_fraction_mean": mean_of("clip_fraction", rows), "approx_kl_mean": mean_of("approx_kl", rows),
            "entropy_start": mean_of("entropy", rows[:HEALTH_WINDOW]),
            "entropy_end": mean_of("entropy", rows[-HEALTH_WINDOW:])}


def final_scores(run_dir: Path, attempts: int) -> dict[str, Any]:
    """The newest checkpoint scored on both sets, as `impulse eval` would, with the shared evaluation seed."""
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig
    from impulse.learner.run import evaluate_run
    from impulse.learner.scoring import kinetix_groups

    config = resolve_config(RunConfig, run_dir / "config.toml", [])
    table = evaluate_run(config, run_dir, levels=EVAL_SETS, attempts=attempts, seed=FINAL_EVAL_SEED)
    handmade = [s["solve_rate"] for name, s in table.items() if "/" not in name]
    return {KINETIX_S: kinetix_groups(table).get("s_all", math.nan),
            HANDMADE: float(np.mean(handmade)) if handmade else math.nan,
            "levels": {name: s["solve_rate"] for name, s in table.items()}}


INTERRUPT_GRACE_S = 90.0
"""Seconds a run interrupted at its time limit has to write its last checkpoint before it is killed."""


def stop_at_timeout(process: subprocess.Popen[bytes], timeout_s: float,
                    grace_s: float = INTERRUPT_GRACE_S) -> int | None:
    """Wait for a run; at `timeout_s` interrupt it as Ctrl-C would, so that it checkpoints the policy it has
    reached and the final scoring sees that policy rather than an older periodic checkpoint; kill it if it has not
    stopped `grace_s` later. Returns the exit status, or None when the run hit its time limit."""
    try:
        return process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=grace_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    return None


def train_one(mode: str, seed: int, root: Path, settings: Settings, steps_per_update: int) -> dict[str, Any]:
    run_dir = root / f"{mode}-seed{seed}"
    log_path = root / f"{mode}-seed{seed}.log"
    progress(f"[{mode} seed {seed}] training ({settings.env_steps:,} env steps); log: {log_path}")
    start = time.monotonic()
    with log_path.open("w") as log:
        process = subprocess.Popen(command(mode, seed, run_dir, settings), cwd=REPO, stdout=log,
                                   stderr=subprocess.STDOUT,
                                   env={**os.environ, "IMPULSE_KINETIX_LEVELS": str(LEVELS_DIR)})
        returncode = stop_at_timeout(process, settings.timeout_s)
    wall_s = time.monotonic() - start
    rows = metrics_rows(run_dir)
    record: dict[str, Any] = {"record": "run", "mode": mode, "seed": seed, "returncode": returncode,
                              "wall_s": round(wall_s, 1), **run_health(rows),
                              "curve": curve(rows, steps_per_update)}
    if returncode != 0:
        progress(f"[{mode} seed {seed}] ended with {'a timeout' if returncode is None else returncode}; "
                 f"tail of the log:\n{''.join(log_path.read_text().splitlines(True)[-15:])}")
    try:
        record["final"] = final_scores(run_dir, settings.attempts)
    except Exception as err:  # noqa: BLE001 - a run without a usable checkpoint is reported, not fatal
        record["final"] = {"error": f"{type(err).__name__}: {err}"}
    final = record["final"]
    progress(f"[{mode} seed {seed}] {wall_s:.0f} s, {record['updates']} updates; final Kinetix S "
             f"{final.get(KINETIX_S, math.nan):.3f}, hand-made {final.get(HANDMADE, math.nan):.3f}")
    return record


def mean_and_error(values: list[float]) -> tuple[float, float]:
    """Mean and standard error across seeds (NaN error with one value)."""
    if not values:
        return math.nan, math.nan
    error = statistics.stdev(values) / math.sqrt(len(values)) if len(values) > 1 else math.nan
    return statistics.fmean(values), error


def time_to(points: list[dict[str, float]], target: float) -> float | None:
    """Seconds from the run's first metrics row to its first evaluation at or above `target` (Kinetix S); the
    untrained policy's point (version 0, which only the evaluator scores) does not count."""
    for point in points:
        if point["env_steps"] > 0 and point[KINETIX_S] >= target:
            return point["time_s"]
    return None


def curve_mean(points: list[dict[str, float]]) -> float:
    """A run's mean Kinetix-S solve rate over its evaluations after training started (version 0 left out): less
    noisy than its final checkpoint alone."""
    trained = [point[KINETIX_S] for point in points if point["env_steps"] > 0 and math.isfinite(point[KINETIX_S])]
    return statistics.fmean(trained) if trained else math.nan


def summarise(runs: list[dict[str, Any]], modes: tuple[str, ...]) -> list[dict[str, Any]]:
    finals = {mode: [r["final"][KINETIX_S] for r in runs if r["mode"] == mode and KINETIX_S in r["final"]]
              for mode in modes}
    means = {mode: mean_and_error(values)[0] for mode, values in finals.items()}
    target = 0.9 * min((m for m in means.values() if math.isfinite(m)), default=math.nan)
    records = []
    for mode in modes:
        mine = [r for r in runs if r["mode"] == mode]
        kinetix = mean_and_error(finals[mode])
        handmade = mean_and_error([r["final"][HANDMADE] for r in mine if HANDMADE in r["final"]])
        over_curve = mean_and_error([curve_mean(r["curve"]) for r in mine if r["curve"]])
        reached = [time_to(r["curve"], target) for r in mine]
        lags = [r["policy_lag_mean"] for r in mine if r["policy_lag_mean"] is not None]
        records.append({
            "record": "summary", "mode": mode, "seeds": [r["seed"] for r in mine],
            "final_kinetix_s": kinetix[0], "final_kinetix_s_se": kinetix[1],
            "final_handmade": handmade[0], "final_handmade_se": handmade[1],
            "curve_kinetix_s": over_curve[0], "curve_kinetix_s_se": over_curve[1],
            "wall_s_mean": statistics.fmean(r["wall_s"] for r in mine) if mine else math.nan,
            "policy_lag_mean": statistics.fmean(lags) if lags else None,
            "batches_dropped": sum(r["batches_dropped"] for r in mine),
            "target_kinetix_s": target,
            "seconds_to_target": reached,
        })
    if set(modes) == set(MODES) and all(finals.values()):
        (fused, fused_se), (dist, dist_se) = (mean_and_error(finals[m]) for m in MODES)
        both = math.sqrt(fused_se**2 + dist_se**2) if math.isfinite(fused_se + dist_se) else math.nan
        ratio = dist / fused if fused > 0 else math.nan
        records.append({"record": "bar", "fused": fused, "distributed": dist, "ratio": ratio,
                        "difference": dist - fused, "two_standard_errors": 2 * both,
                        "holds": bool(ratio >= 0.9 or abs(dist - fused) <= 2 * both)})
    return records


def plot(runs: list[dict[str, Any]], path: Path, settings: Settings) -> None:
    step = settings.eval_every * update_steps(settings.overrides) / 1e6  # env steps (millions) between points
    panels = []
    for level_set in (KINETIX_S, HANDMADE):
        series = []
        for mode in settings.modes:
            mine = [r for r in runs if r["mode"] == mode]
            by_x: dict[float, list[float]] = {}
            for r in mine:
                xs = [p["env_steps"] / 1e6 for p in r["curve"]]
                ys = [p[level_set] for p in r["curve"]]
                series.append(Series(f"{mode}, one seed", xs, ys, MODE_COLORS[mode], width=1, dashed=True,
                                     markers=False))
                for x, y in zip(xs, ys, strict=True):  # the evaluator's points fall near the nominal ones
                    by_x.setdefault(round(x / step) * step, []).append(y)
            xs = sorted(by_x)
            series.append(Series(f"{mode}, mean of {len(mine)} seeds", xs,
                                 [statistics.fmean(by_x[x]) for x in xs], MODE_COLORS[mode]))
        panels.append(Panel(SET_TITLES[level_set], series, "env steps (millions)", "solve rate", (0.0, 1.0)))
    render(panels, path, f"Fused vs distributed ({settings.curriculum}, random S levels)")
    progress(f"plot: {path}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench learning", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--curriculum", default="sfl", help="curriculum method (default sfl)")
    parser.add_argument("--env-steps", type=int, default=128 * 4096, help="env-step budget per run")
    parser.add_argument("--eval-every", type=int, default=16, help="updates between evaluation points")
    parser.add_argument("--attempts", type=int, default=20, help="episodes per level (Kinetix's protocol: 20)")
    parser.add_argument("--actors", type=int, default=2, help="actors of the distributed mode")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for every run (after the CPU settings)")
    parser.add_argument("--timeout", type=float, default=3600.0,
                        help="seconds a run may train; then it is interrupted, checkpoints and is scored")
    parser.add_argument("--plot", type=Path, help="write the curves here (PNG)")
    parser.add_argument("--keep", type=Path, help="keep the run directories and logs here (default: a temp dir)")
    args = parser.parse_args(argv)
    if not LEVELS_DIR.is_dir():
        raise SystemExit(f"Kinetix levels not found at {LEVELS_DIR}: the benchmark scores on Kinetix's S levels "
                         "(the shared/ folder beside the checkout, or $IMPULSE_KINETIX_LEVELS)")
    settings = Settings(tuple(args.modes), tuple(args.seeds), args.curriculum, args.env_steps, args.eval_every,
                        args.attempts, args.actors, tuple(args.overrides), args.timeout)
    steps_per_update = update_steps(settings.overrides)
    emit({"record": "config", **environment(), "settings": dataclasses.asdict(settings) | {"quick": QUICK},
          "steps_per_update": steps_per_update, "commit": _commit(),
          "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    root = args.keep or Path(tempfile.mkdtemp(prefix="impulse-learning-"))
    root.mkdir(parents=True, exist_ok=True)
    runs = []
    try:
        for seed in settings.seeds:  # modes alternate, so a drift of the machine's load hits both alike
            for mode in settings.modes:
                record = train_one(mode, seed, root, settings, steps_per_update)
                emit(record)
                runs.append(record)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    for record in summarise(runs, settings.modes):
        emit(record)
        progress(json.dumps(record))
    if args.plot is not None:
        plot(runs, args.plot, settings)
    return 0


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


if __name__ == "__main__":
    raise SystemExit(main())
