"""`impulse import-kinetix` checked against Kinetix 3.0.2 itself, in two parts.

``nets``: in the reference virtualenv (benchmarks/reference_env.py), Kinetix's own code builds each network type
(entity transformer, with the legacy entity id, with full attention and ReLU; permutation-invariant MLP; flat MLP
with multi-discrete, discrete and continuous actions), perturbs its parameters, saves it as its training scripts
do (full_model.pbz2) and in its pretrained format (params.safetensors + config.json), and computes the action
distribution and value on observations of shared levels (`_reference_kinetix_nets.py nets`). Here each file is
imported (the .pbz2 with the run's model settings, as `--kinetix-config` would give them) and run on the same
observations. Printed per (variant, format): the largest absolute difference of the per-dimension
log-probabilities (Gaussian: means and log-stds) and of the values; within tolerance means every output is
within ``--tolerance`` x (1 + scale) of Kinetix's, the scale being the largest |output| of that observation's
distribution, or |value| (default 1e-5: absolute for outputs of order 1, relative for large ones, whose float32
rounding grows with them).

``policy``: a policy trained briefly by Kinetix (its PPO rollout-and-update function, entity transformer,
multi-discrete actions) on one shared level, then evaluated from the level's start by both systems, Kinetix's
env and network there, ``impulse import-kinetix`` + our evaluation here, ``--episodes`` sampled episodes each.
Printed: both solve rates and the two-proportion z statistic (|z| < 2: equal within sampling error at about
95 %). The two physics engines are not bit-identical, so this checks the whole path, not only the network.

    impulse bench kinetix_import nets
    impulse bench kinetix_import nets --sizes s --variants transformer flat
    impulse bench kinetix_import nets --work DIR --reuse        # compare again without remaking Kinetix's files
    impulse bench kinetix_import policy --level s/h4_thrust_aim --updates 12 --episodes 512
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from impulse.benchmarks._harness import LEVELS_DIR, emit, environment, progress, require_levels
from impulse.benchmarks.reference_env import run_reference
from impulse.engine.env.observation_types import EntityObservation
from impulse.learner.kinetix_import import import_kinetix, policy_outputs, read_kinetix_checkpoint

REFERENCE_SCRIPT = Path(__file__).resolve().parent / "_reference_kinetix_nets.py"
NET_LEVELS = {
    "s": ["s/h0_weak_thrust", "s/h2_one_wheel_car", "s/h4_thrust_aim", "s/h6_unicycle_right",
          "s/h9_explode_then_thrust_over"],
    "m": ["m/h0_unicycle", "m/h5_angry_birds", "m/h8_weird_vehicle", "m/arm_hard"],
}
ENTITY_VARIANTS = ("transformer", "transformer_legacy_id", "transformer_full_relu", "entity")
FLAT_VARIANTS = ("flat", "flat_discrete", "flat_continuous")
REFERENCE_TIMEOUT_S = 3600.0


def level_path(name: str) -> Path:
    path = Path(name)
    if path.is_file():
        return path
    return LEVELS_DIR / (name if name.endswith(".json") else f"{name}.json")


def observation_of(arrays: dict[str, np.ndarray]) -> EntityObservation | jax.Array:
    if "obs_flat" in arrays:
        return jnp.asarray(arrays["obs_flat"])
    return EntityObservation(**{f.name: jnp.asarray(arrays[f"obs_{f.name}"])
                                for f in dataclasses.fields(EntityObservation)})


def compare_nets(args: argparse.Namespace, work: Path) -> list[dict[str, Any]]:
    results = []
    for size in args.sizes:
        variants = [v for v in args.variants if v in ENTITY_VARIANTS or size == "s"]
        if not variants:
            continue
        levels = [str(level_path(name)) for name in NET_LEVELS[size]]
        saved = work / size / "records.jsonl"
        if args.reuse and saved.is_file():
            progress(f"kinetix_import nets: reusing Kinetix's files and records in {saved.parent}")
            records = [json.loads(line) for line in saved.read_text().splitlines()]
        else:
            progress(f"kinetix_import nets: Kinetix builds {', '.join(variants)} on {len(levels)} {size.upper()} "
                     "levels")
            records = run_reference(["nets", "--levels", *levels, "--out", str(work / size), "--variants",
                                     *variants], REFERENCE_TIMEOUT_S, script=REFERENCE_SCRIPT)
            saved.write_text("".join(json.dumps(r) + "\n" for r in records))
        for record in records:
            arrays = dict(np.load(record["outputs"]))
            expected = (np.concatenate([arrays["mean"], np.broadcast_to(arrays["log_std"], arrays["mean"].shape)],
                                       axis=-1) if "mean" in arrays else arrays["log_probs"])
            for fmt, path, options in (("pbz2", record["pbz2"], record["model"]),
                                       ("pretrained", record["pretrained"], {})):
                imported = import_kinetix(read_kinetix_checkpoint(path), options)
                distribution, value = policy_outputs(imported, observation_of(arrays))
                diff_dist = float(np.abs(distribution - expected).max())
                diff_value = float(np.abs(value - arrays["value"]).max())
                within = all(bool(np.all(np.abs(ours - theirs) <= args.tolerance * (1 + scale)))
                             for ours, theirs, scale in (
                                 (distribution, expected, np.abs(expected).max(axis=-1, keepdims=True)),
                                 (value, arrays["value"], np.abs(arrays["value"]))))
                result = {
                    "check": "nets", "variant": record["variant"], "format": fmt, "size": size,
                    "network": imported.network.kind, "parameters": record["parameters"],
                    "observations": record["observations"], "levels": len(levels),
                    "max_abs_diff_distribution": diff_dist, "max_abs_diff_value": diff_value,
                    "max_abs_value": float(np.abs(arrays["value"]).max()),
                    "max_abs_log_prob": float(np.abs(expected).max()), "tolerance": args.tolerance,
                    "within_tolerance": within,
                    "reference": {k: record[k] for k in ("jax_version", "backend", "device")}, **environment(),
                }
                emit(result)
                results.append(result)
    return results


def two_proportion_z(solved_a: int, n_a: int, solved_b: int, n_b: int) -> float:
    pooled = (solved_a + solved_b) / (n_a + n_b)
    spread = math.sqrt(max(pooled * (1 - pooled) * (1 / n_a + 1 / n_b), 1e-12))
    return (solved_a / n_a - solved_b / n_b) / spread


def compare_policy(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    from impulse.deploy.cli import main as impulse
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig
    from impulse.learner.run import evaluate_run

    level = str(level_path(args.level))
    progress(f"kinetix_import policy: Kinetix trains on {args.level} for {args.updates} updates")
    records = run_reference(["train", "--level", level, "--out", str(work / "trained"), "--updates",
                             str(args.updates), "--num-envs", str(args.num_envs), "--num-steps", str(args.num_steps)],
                            REFERENCE_TIMEOUT_S, script=REFERENCE_SCRIPT)
    for record in records[:-1]:
        progress(f"  update {record['update']}: solve rate of finished episodes {record['solve_rate']:.2f}")
    saved = records[-1]
    progress("kinetix_import policy: Kinetix evaluates it")
    theirs = run_reference(["evaluate", "--level", level, "--checkpoint", saved["saved"], "--episodes",
                            str(args.episodes), "--seed", str(args.seed)], REFERENCE_TIMEOUT_S,
                           script=REFERENCE_SCRIPT)[-1]
    run_dir = work / "imported"
    progress("kinetix_import policy: impulse import-kinetix, then our evaluation")
    with contextlib.redirect_stdout(sys.stderr):  # stdout carries only this benchmark's JSON lines
        status = impulse(["import-kinetix", saved["saved"], "--out", str(run_dir), "--kinetix-config",
                          str(work / "trained" / "model.json")])
    if status != 0:
        raise SystemExit(f"impulse import-kinetix failed with status {status}")
    config = resolve_config(RunConfig, run_dir / "config.toml")
    table = evaluate_run(config, run_dir, levels=level, attempts=args.episodes, seed=args.seed)
    ours = next(iter(table.values()))
    ours_solved = round(ours["solve_rate"] * args.episodes)
    result = {
        "check": "policy", "level": args.level, "updates": args.updates, "num_envs": args.num_envs,
        "num_steps": args.num_steps, "train_env_steps": saved["env_steps"], "train_s": saved["train_s"],
        "training_curve": [r["solve_rate"] for r in records[:-1]], "episodes": args.episodes,
        "kinetix_solve_rate": theirs["solve_rate"], "impulse_solve_rate": ours["solve_rate"],
        "impulse_mean_return": ours["mean_return"],
        "z": two_proportion_z(theirs["solved"], args.episodes, ours_solved, args.episodes),
        "reference": {k: theirs[k] for k in ("jax_version", "backend", "device")}, **environment(),
    }
    result["within_sampling_error"] = abs(result["z"]) < 2.0
    emit(result)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench kinetix_import", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("part", nargs="?", choices=("nets", "policy", "all"), default="all")
    parser.add_argument("--sizes", nargs="+", default=["s", "m"], choices=list(NET_LEVELS))
    parser.add_argument("--variants", nargs="+", default=[*ENTITY_VARIANTS, *FLAT_VARIANTS],
                        choices=[*ENTITY_VARIANTS, *FLAT_VARIANTS])
    parser.add_argument("--tolerance", type=float, default=1e-5,
                        help="each output must be within TOL x (1 + scale) of Kinetix's, scale being the largest "
                        "|output| of the observation's distribution, or |value|: absolute for outputs of order 1, "
                        "relative (float32 rounding) for large ones")
    parser.add_argument("--reuse", action="store_true",
                        help="nets: reuse the Kinetix files and records already in --work instead of remaking them")
    parser.add_argument("--level", default="s/h4_thrust_aim", help="level the policy is trained and evaluated on")
    parser.add_argument("--updates", type=int, default=12)
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--num-steps", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, help="keep the files here (default: a temporary folder)")
    args = parser.parse_args(argv)
    require_levels()
    with tempfile.TemporaryDirectory(prefix="kinetix-import-") as scratch:
        work = args.work or Path(scratch)
        ok = True
        if args.part in ("nets", "all"):
            ok &= all(r["within_tolerance"] for r in compare_nets(args, work / "nets"))
        if args.part in ("policy", "all"):
            ok &= compare_policy(args, work / "policy")["within_sampling_error"]
    emit({"check": "summary", "all_within": bool(ok), "arguments": json.loads(json.dumps(vars(args), default=str))})
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
