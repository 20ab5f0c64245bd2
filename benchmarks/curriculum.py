"""Curricula compared: DR, PLR, ACCEL and SFL each train a fresh agent on random S levels for the same env-step
budget (fused mode, `impulse train`'s own trainer), and every `--eval-every` updates the agent is scored zero-shot
on levels it never trained on: (a) our hand-made S levels and (b) Kinetix's S levels (../shared/kinetix-levels/s).

What is timed and counted:
- env steps are training steps only (updates x envs x steps), the same for every method. Curriculum work beyond
  them is not charged to the budget: DR's and the candidates' no-op filter (`filter_ratio` x envs levels played
  for `filter_steps` with the zero action per new batch), and ACCEL's mutations. Wall seconds show that cost.
- evaluation: `learner.evaluate.evaluate`, `--attempts` episodes per level from its start, stochastic policy (as
  Kinetix scores hand-made levels); the solve rate of a set is the mean over its levels. Every method is evaluated
  with the same keys at the same update, so the evaluation noise is shared across methods.
- training solve rate: solved / finished episodes in the training batches since the previous evaluation point
  (levels differ by method, so it says how hard each curriculum's levels were, not how good the agent is).

Output: JSON lines on stdout (`record` = "config", "eval", "summary"), progress and the final table on stderr, and
a PNG of the solve rate against env steps (one panel per evaluation set plus the training levels, one line per
method, mean over seeds) at `--plot`.

    impulse bench curriculum --quick                          # CPU: 4 methods, small network and budget
    impulse bench curriculum --gpu --methods plr sfl --seeds 0 1 2
    impulse bench curriculum --quick --set curriculum.buffer_size=128 --set sfl:curriculum.sfl_ratio=0.25
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from impulse.benchmarks._harness import LEVELS_DIR, REPO, emit, environment, progress
from impulse.benchmarks.plot import PALETTE, Panel, Series, mean_curves, render
from impulse.curriculum.config import METHODS
from impulse.curriculum.stats import buffer_summary
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.engine.env.spec import env_from_config
from impulse.engine.levels.level import Level
from impulse.engine.levels.sets import HANDMADE, LevelSetError, load_level_set
from impulse.engine.physics.sizes import SceneSizes
from impulse.learner.evaluate import evaluate
from impulse.learner.run import build

EVAL_SETS = ("handmade", "kinetix_s")
EVAL_TITLES = {"handmade": "our hand-made S levels", "kinetix_s": "Kinetix S levels", "train": "training levels"}
BUFFER_KEYS = ("buffer_fill", "score_mean", "learnable", "never_solved", "always_solved", "count_inserted",
               "count_evicted", "generation_mean")

QUICK = [
    "network.kind=entity", "network.width=64", "network.depth=2",
    "ppo.num_envs=64", "ppo.num_steps=64", "ppo.num_minibatches=4", "ppo.update_epochs=4",
    "ppo.learning_rate=3e-4", "ppo.anneal_lr=false",
    "curriculum.buffer_size=256",
]
"""configs/quick-cpu.toml's learner (which solves an easy hand-made level in 20 updates on a laptop CPU), with a
buffer that fills within the first few dozen updates of a short run."""

GPU = [
    "network.kind=transformer",
    "ppo.num_envs=2048", "ppo.num_steps=64", "ppo.num_minibatches=32", "ppo.update_epochs=8",
    "ppo.learning_rate=1e-4", "ppo.anneal_lr=true",
    "curriculum.buffer_size=4000", "sfl:curriculum.buffer_size=1024",
]
"""Kinetix's PPO and curriculum settings at its throughput benchmark's rollout length (2,048 envs x 64 steps,
8 epochs x 32 minibatches, transformer, buffer 4,000 for PLR/ACCEL and 1,024 for SFL)."""

PRESETS = {
    "quick": {"overrides": QUICK, "env_steps": 524_288, "eval_every": 16, "attempts": 16},
    "gpu": {"overrides": GPU, "env_steps": 20_971_520, "eval_every": 10, "attempts": 20},
}


@dataclass(frozen=True)
class EvalSet:
    """A fixed batch of evaluation levels, or why there is none."""

    name: str
    names: list[str]
    levels: Level | None
    skipped: str = ""


def method_overrides(items: list[str], method: str) -> list[str]:
    """The `KEY=VALUE` items that apply to `method`: unprefixed ones, and `METHOD:KEY=VALUE` for this method."""
    chosen = []
    for item in items:
        key, _, value = item.partition("=")
        prefix, sep, rest = key.partition(":")
        if not sep:
            chosen.append(item)
        elif prefix not in METHODS:
            raise ValueError(f"override {item!r}: {prefix!r} is not a method ({', '.join(METHODS)})")
        elif prefix == method:
            chosen.append(f"{rest}={value}")
    return chosen


def make_config(method: str, seed: int, env_steps: int, config_path: Path | None, overrides: list[str]) -> RunConfig:
    """The training config of one (method, seed): random S levels, the preset, method defaults, then `--set`."""
    items = ["env.levels=random", "env.size=s", f"curriculum={method}", f"seed={seed}",
             f"total_env_steps={env_steps}"]
    return resolve_config(RunConfig, config_path, items + method_overrides(overrides, method))


def load_eval_sets(sizes: SceneSizes, kinetix_dir: Path) -> list[EvalSet]:
    """Our hand-made levels that fit S and the Kinetix S folder; a set that cannot be loaded is kept as skipped,
    with the reason, so the output says why it is missing rather than silently leaving it out."""
    sets = []
    for name, source in (("handmade", HANDMADE), ("kinetix_s", str(kinetix_dir))):
        if name == "kinetix_s" and not kinetix_dir.is_dir():
            reason = f"{kinetix_dir} not found (the shared Kinetix levels beside the checkout)"
            progress(f"skipping the Kinetix S evaluation set: {reason}")
            sets.append(EvalSet(name, [], None, reason))
            continue
        try:
            names, levels = load_level_set(source, sizes)
        except LevelSetError as err:
            progress(f"skipping evaluation set {name}: {err}")
            sets.append(EvalSet(name, [], None, str(err)))
            continue
        sets.append(EvalSet(name, names, levels))
    return sets


def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _json_number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def train_and_evaluate(method: str, seed: int, config: RunConfig, eval_sets: list[EvalSet], eval_every: int,
                       attempts: int, eval_seed: int) -> list[dict[str, Any]]:
    """Train one agent with `method`, evaluating it at update 0, every `eval_every` updates and at the end; emits
    and returns the eval records."""
    start = time.perf_counter()
    trainer, agent, _, _ = build(config)
    init, iterate = trainer.jitted()
    carry = init(jax.random.PRNGKey(seed), None)
    jax.block_until_ready(carry)
    compile_start = time.perf_counter()
    step = iterate.lower(carry, None).compile()
    compile_s = time.perf_counter() - compile_start
    steps_per_update = config.ppo.num_envs * config.ppo.num_steps
    num_updates = trainer.num_updates
    emit({"benchmark": "curriculum", "record": "config", "method": method, "seed": seed,
          "num_updates": num_updates, "steps_per_update": steps_per_update, "env_steps": num_updates * steps_per_update,
          "compile_s": compile_s, "setup_s": time.perf_counter() - start,
          "parameters": int(sum(x.size for x in jax.tree.leaves(carry.train.params))),
          "network": config.network.kind, "width": config.network.width, "depth": config.network.depth,
          "num_envs": config.ppo.num_envs, "num_steps": config.ppo.num_steps,
          "update_epochs": config.ppo.update_epochs, "num_minibatches": config.ppo.num_minibatches,
          "learning_rate": config.ppo.learning_rate, "anneal_lr": config.ppo.anneal_lr,
          "ppo": dataclasses.asdict(config.ppo), "curriculum": dataclasses.asdict(config.curriculum),
          "eval_sets": {s.name: (s.names if s.levels is not None else f"skipped: {s.skipped}") for s in eval_sets},
          "attempts": attempts, **environment()})
    progress(f"{method} seed {seed}: compiled in {compile_s:.1f} s; {num_updates} updates of {steps_per_update} "
             "env steps")

    records: list[dict[str, Any]] = []
    train_s, eval_s = 0.0, 0.0
    window: dict[str, float] = {}

    def evaluate_now(update: int) -> None:
        nonlocal eval_s
        eval_start = time.perf_counter()
        key = jax.random.fold_in(jax.random.PRNGKey(eval_seed), update)
        record: dict[str, Any] = {"benchmark": "curriculum", "record": "eval", "method": method, "seed": seed,
                                  "update": update, "env_steps": update * steps_per_update}
        for i, eval_set in enumerate(eval_sets):
            if eval_set.levels is None:
                record[f"{eval_set.name}_solve_rate"] = None
                continue
            scores = evaluate(agent, carry.train.params, trainer.env_params, eval_set.levels,
                              jax.random.fold_in(key, i), attempts=attempts)
            record[f"{eval_set.name}_solve_rate"] = float(scores.solve_rate.mean())
            record[f"{eval_set.name}_levels"] = {n: float(r) for n, r in zip(eval_set.names, scores.solve_rate)}
        episodes = window.get("episodes", 0.0)
        record["train_solve_rate"] = window["solved"] / episodes if episodes > 0 else None
        record["train_episodes"] = int(episodes)
        updates_in_window = window.get("updates", 0.0)
        for origin in ("new", "replay", "mutated"):
            total = window.get(f"levels_{origin}", 0.0)
            record[f"levels_{origin}"] = total / updates_in_window if updates_in_window else None
        if carry.curriculum is not None:
            summary = buffer_summary(carry.curriculum, agent.spec.sizes, update)
            record.update({k: _json_number(float(summary[k])) for k in BUFFER_KEYS if k in summary})
        eval_s += time.perf_counter() - eval_start
        record.update({"wall_s": time.perf_counter() - start, "train_s": train_s, "eval_s": eval_s,
                       "compile_s": compile_s})
        emit(record)
        records.append(record)
        window.clear()
        shown = "  ".join(f"{s.name} {record[f'{s.name}_solve_rate']:.3f}" for s in eval_sets if s.levels is not None)
        train_rate = record["train_solve_rate"]
        progress(f"{method} seed {seed} update {update:>5} ({record['env_steps']:,} steps, {record['wall_s']:.0f} s): "
                 f"{shown}  train {'-' if train_rate is None else f'{train_rate:.3f}'}")

    evaluate_now(0)
    for update in range(1, num_updates + 1):
        tick = time.perf_counter()
        carry, metrics = step(carry, None)
        metrics = jax.device_get(metrics)
        train_s += time.perf_counter() - tick
        window["updates"] = window.get("updates", 0.0) + 1
        for name in ("episodes", "solved", "levels_new", "levels_replay", "levels_mutated"):
            if name in metrics:
                window[name] = window.get(name, 0.0) + float(metrics[name])
        if update % eval_every == 0 or update == num_updates:
            evaluate_now(update)
    return records


def summarise(records: list[dict[str, Any]], methods: list[str], eval_sets: list[EvalSet]) -> list[dict[str, Any]]:
    """Per method: the last evaluation point's solve rates, mean and spread over seeds."""
    rows = []
    for method in methods:
        finals: dict[int, dict[str, Any]] = {}
        for record in records:
            if record["method"] == method:
                finals[record["seed"]] = record  # records come in update order per seed, so the last one stays
        if not finals:
            continue
        last = list(finals.values())
        row: dict[str, Any] = {"benchmark": "curriculum", "record": "summary", "method": method,
                               "seeds": sorted(finals), "env_steps": last[0]["env_steps"],
                               "wall_s_mean": _mean([r["wall_s"] for r in last])}
        for name in [s.name for s in eval_sets] + ["train"]:
            values = [r[f"{name}_solve_rate"] for r in last if r.get(f"{name}_solve_rate") is not None]
            row[f"{name}_solve_rate"] = float(np.mean(values)) if values else None
            row[f"{name}_solve_rate_std"] = float(np.std(values)) if len(values) > 1 else None
        rows.append(row)
    return rows


def table(rows: list[dict[str, Any]], eval_sets: list[EvalSet]) -> str:
    """The final solve rates as a Markdown table (what RESULTS.md quotes)."""
    names = [s.name for s in eval_sets] + ["train"]
    header = "| method | seeds | env steps | " + " | ".join(EVAL_TITLES[n] for n in names) + " | wall (s) |"
    lines = [header, "|---|---:|---:|" + "---:|" * len(names) + "---:|"]
    for row in rows:
        cells = []
        for name in names:
            value, spread = row[f"{name}_solve_rate"], row[f"{name}_solve_rate_std"]
            cells.append("n/a" if value is None else f"{value:.3f}" + (f" ± {spread:.3f}" if spread else ""))
        lines.append(f"| {row['method'].upper()} | {len(row['seeds'])} | {row['env_steps']:,} | "
                     + " | ".join(cells) + f" | {row['wall_s_mean']:.0f} |")
    return "\n".join(lines)


def plot(records: list[dict[str, Any]], methods: list[str], eval_sets: list[EvalSet], path: Path,
         title: str) -> Path:
    """Solve rate against env steps: a panel per evaluation set and one for the training levels, a line per method
    (the mean over seeds)."""
    colors = {method: PALETTE[i] for i, method in enumerate(METHODS)}
    # Methods often coincide (PLR and ACCEL play the same new levels until the buffer fills): lines drawn earlier
    # are wider and every other one is dashed, so a line lying on another still shows.
    widths = {method: 2 + 2 * (len(methods) - 1 - i) for i, method in enumerate(methods)}
    panels = []
    for name in [s.name for s in eval_sets] + ["train"]:
        curves = mean_curves(records, "env_steps", f"{name}_solve_rate", "method")
        series = [Series(m.upper(), *curves[m], color=colors[m], width=widths[m], dashed=i % 2 == 1)
                  for i, m in enumerate(methods) if m in curves]
        skipped = any(s.name == name and s.levels is None for s in eval_sets)
        panels.append(Panel(EVAL_TITLES[name], series, x_label="env steps", y_label="solve rate",
                            note="skipped: levels not found (see the config record)" if skipped else "no data"))
    return render(panels, path, title)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench curriculum", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    preset = parser.add_mutually_exclusive_group()
    preset.add_argument("--quick", action="store_true",
                        help="CPU size (the default): entity network 64 x 2, 64 envs x 64 steps, 4 x 4 minibatch "
                        "epochs, lr 3e-4 constant, buffer 256, 655,360 env steps per method, eval every 20 updates "
                        "over 8 attempts")
    preset.add_argument("--gpu", "--kinetix-settings", dest="gpu", action="store_true",
                        help="GPU size: Kinetix's transformer and PPO settings at 2,048 envs x 64 steps, buffer 4,000 "
                        "(SFL 1,024), 20,971,520 env steps per method, eval every 10 updates over 20 attempts")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--env-steps", type=int, help="training env steps per method and seed (rounded up to whole "
                        "updates)")
    parser.add_argument("--eval-every", type=int, help="updates between evaluation points")
    parser.add_argument("--attempts", type=int, help="evaluation episodes per level")
    parser.add_argument("--eval-seed", type=int, default=12345, help="seed of the evaluation keys (shared by methods)")
    parser.add_argument("--config", type=Path, help="a TOML run config applied before the preset's overrides")
    parser.add_argument("--set", action="append", default=[], metavar="[METHOD:]KEY=VALUE",
                        help="a config override for every method, or for one with a METHOD: prefix (repeatable)")
    parser.add_argument("--kinetix-levels", type=Path, default=LEVELS_DIR / "s",
                        help="folder of Kinetix S level files (default ../shared/kinetix-levels/s)")
    parser.add_argument("--plot", type=Path, help="PNG to write (default benchmarks/results/"
                        "curriculum-<backend>-<date>.png)")
    args = parser.parse_args(argv)
    chosen = PRESETS["gpu" if args.gpu else "quick"]
    env_steps = args.env_steps or chosen["env_steps"]
    eval_every = args.eval_every or chosen["eval_every"]
    attempts = args.attempts or chosen["attempts"]
    if eval_every < 1 or attempts < 1 or env_steps < 1:
        parser.error("--env-steps, --eval-every and --attempts must be positive")
    overrides = chosen["overrides"] + args.set
    try:
        configs = {(m, s): make_config(m, s, env_steps, args.config, overrides)
                   for m in args.methods for s in args.seeds}
    except ValueError as err:  # an unknown METHOD: prefix, or a key or value the config rejects
        parser.error(str(err))
    sizes = build_sizes(next(iter(configs.values())))
    eval_sets = load_eval_sets(sizes, args.kinetix_levels)
    date = datetime.date.today().isoformat()
    plot_path = args.plot or REPO / "benchmarks" / "results" / f"curriculum-{jax.default_backend()}-{date}.png"

    start = time.perf_counter()
    records: list[dict[str, Any]] = []
    for (method, seed), config in configs.items():
        records += train_and_evaluate(method, seed, config, eval_sets, eval_every, attempts, args.eval_seed)
        plot(records, args.methods, eval_sets, plot_path, _title(configs, args.seeds, attempts))
    rows = summarise(records, args.methods, eval_sets)
    for row in rows:
        emit(row)
    progress(f"\nfinal solve rates ({attempts} attempts per level, stochastic policy), "
             f"{time.perf_counter() - start:.0f} s in all:\n{table(rows, eval_sets)}\nplot: {plot_path}")
    return 0


def build_sizes(config: RunConfig) -> SceneSizes:
    """The scene sizes of the run's environment, without building a trainer."""
    spec, _ = env_from_config(config.env)
    return spec.sizes


def _title(configs: dict[tuple[str, int], RunConfig], seeds: list[int], attempts: int) -> str:
    config = next(iter(configs.values()))
    seeds_text = f"{len(seeds)} seed{'s' if len(seeds) > 1 else ''}" + (" (mean)" if len(seeds) > 1 else "")
    return (f"Zero-shot solve rate vs training env steps, random S levels; {config.network.kind} "
            f"{config.network.width}x{config.network.depth}, {config.ppo.num_envs} envs x {config.ppo.num_steps} "
            f"steps; {seeds_text}; {attempts} attempts/level; {jax.default_backend()}")


if __name__ == "__main__":
    raise SystemExit(main())
