"""The GPU table of benchmarks/RESULTS.md, from the JSON lines one `make bench-gpu` run appended.

One row per size (S, M, L), steps per second: the engine (ours with the XLA solver and with the fused kernel, and
Jax2D, at the largest batch measured), the environment (ours and Kinetix's), end-to-end training (our fused
trainer with each physics backend) and the distributed runtime (learner + 1, 2, 4 actors), then the ratios the
GPU issue's acceptance names. A run is the lines after a `{"bench_gpu": "start"}` line; a start line with
`"call": N` for N > 1 continues the run before it (a run split over several calls to a lent machine, docs/gpu.md).
The newest run of the file is taken unless `--run` picks another (0 = the first). A figure the run did not produce
prints as "-".

    impulse bench gpu_table benchmarks/results/gpu-2026-11-24.jsonl
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

SIZES = ("s", "m", "l")
COLUMNS = (
    ("engine, ours (XLA)", "engine_xla"),
    ("engine, ours (fused kernel)", "engine_pallas"),
    ("engine, Jax2D", "engine_jax2d"),
    ("env, ours", "env_ours"),
    ("env, Kinetix", "env_kinetix"),
    ("training, fused (XLA)", "train_xla"),
    ("training, fused (kernel)", "train_pallas"),
    ("distributed, 1 actor", "distributed_1"),
    ("distributed, 2 actors", "distributed_2"),
    ("distributed, 4 actors", "distributed_4"),
)


def runs(lines: Iterable[str]) -> list[list[dict[str, Any]]]:
    """The file's records grouped by run (a start line opens one, unless it continues the run before it as call 2,
    3, ...); lines that are not JSON objects are skipped."""
    grouped: list[list[dict[str, Any]]] = []
    for line in lines:
        line = line.strip()
        if not line.startswith("{"):
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        continues = isinstance(record.get("call"), int) and record["call"] > 1
        if (record.get("bench_gpu") == "start" and not continues) or not grouped:
            grouped.append([])
        grouped[-1].append(record)
    return grouped


def _largest_batch(records: list[dict[str, Any]], rate: str) -> float | None:
    """The rate at the largest num_envs among `records` (the GPU figure; small batches measure latency)."""
    timed = [r for r in records if isinstance(r.get(rate), (int, float))]
    if not timed:
        return None
    return max(timed, key=lambda r: r.get("num_envs", 0))[rate]


def figures(run: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """{size: {column key: steps per second}} for one run."""
    table: dict[str, dict[str, float | None]] = {}
    for size in SIZES:
        of_size = [r for r in run if r.get("size") == size]

        def pick(predicate, rate: str = "steps_per_s", rows: list[dict[str, Any]] = of_size) -> float | None:
            return _largest_batch([r for r in rows if predicate(r)], rate)

        row = {
            "engine_xla": pick(lambda r: r.get("system") == "impulse" and r.get("solver") == "phased"
                               and r.get("physics_backend", "xla") == "xla"),
            "engine_pallas": pick(lambda r: r.get("system") == "impulse" and r.get("physics_backend") == "pallas"),
            "engine_jax2d": pick(lambda r: r.get("system") == "jax2d" and "kind" not in r),
            "env_ours": pick(lambda r: r.get("system") == "impulse-env"),
            "env_kinetix": pick(lambda r: r.get("system") == "kinetix-env"),
            "train_xla": pick(lambda r: r.get("system") == "impulse-fused-ppo"
                              and r.get("physics_backend", "xla") == "xla", "env_steps_per_s"),
            "train_pallas": pick(lambda r: r.get("system") == "impulse-fused-ppo"
                                 and r.get("physics_backend") == "pallas", "env_steps_per_s"),
        }
        for actors in (1, 2, 4):
            row[f"distributed_{actors}"] = pick(
                lambda r, n=actors: r.get("system") == "impulse-distributed" and r.get("actors") == n,
                "env_steps_per_s")
        table[size] = row
    return table


def _cell(value: float | None) -> str:
    if value is None:
        return "-"
    if value >= 1e6:
        return f"{value / 1e6:.2f}M"
    if value >= 1e3:
        return f"{value / 1e3:.1f}k"
    return f"{value:.0f}"


def _ratio(numerator: float | None, denominator: float | None) -> str:
    return "-" if numerator is None or not denominator else f"{numerator / denominator:.2f}x"


def markdown(run: list[dict[str, Any]]) -> str:
    """The table, a ratio table, and a line naming the run (date, commit, device, JAX version)."""
    start = next((r for r in run if r.get("bench_gpu") == "start"), {})
    calls = sum(r.get("bench_gpu") == "start" for r in run)
    device = next((r for r in run if "device" in r and "jax_version" in r), {})
    table = figures(run)
    split = f" (in {calls} calls)" if calls > 1 else ""
    lines = [f"Run of {start.get('utc', '?')}{split} at commit {start.get('commit', '?')}, device "
             f"{device.get('device', '?')}, JAX {device.get('jax_version', '?')}; steps per second at the largest "
             "batch measured.", "",
             "| size | " + " | ".join(title for title, _ in COLUMNS) + " |",
             "|---|" + "---|" * len(COLUMNS)]
    for size in SIZES:
        lines.append(f"| {size.upper()} | " + " | ".join(_cell(table[size][key]) for _, key in COLUMNS) + " |")
    lines += ["", "| size | engine: XLA / Jax2D | engine: kernel / Jax2D (goal 10x) | engine: kernel / XLA | "
              "training: kernel / XLA | env: ours / Kinetix |", "|---|---|---|---|---|---|"]
    for size in SIZES:
        row = table[size]
        lines.append(f"| {size.upper()} | {_ratio(row['engine_xla'], row['engine_jax2d'])} | "
                     f"{_ratio(row['engine_pallas'], row['engine_jax2d'])} | "
                     f"{_ratio(row['engine_pallas'], row['engine_xla'])} | "
                     f"{_ratio(row['train_pallas'], row['train_xla'])} | "
                     f"{_ratio(row['env_ours'], row['env_kinetix'])} |")
    lines += ["", "Kinetix's PPO is not in the run: its training script is not part of the kinetix-env package."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench gpu_table", description=__doc__.split("\n")[0])
    parser.add_argument("path", type=Path, help="a JSON-lines file of make bench-gpu")
    parser.add_argument("--run", type=int, default=-1, help="which run of the file (default: the newest)")
    args = parser.parse_args(argv)
    if not args.path.is_file():
        raise SystemExit(f"no such file: {args.path}")
    grouped = runs(args.path.read_text().splitlines())
    if not grouped:
        raise SystemExit(f"{args.path} holds no JSON lines")
    try:
        run = grouped[args.run]
    except IndexError:
        raise SystemExit(f"{args.path} holds {len(grouped)} run(s); --run {args.run} is not one") from None
    print(markdown(run))


if __name__ == "__main__":
    main()
