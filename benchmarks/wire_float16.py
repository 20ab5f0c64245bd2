"""Does learning notice float16 features on the wire (`bus.wire_float16`)? Two measurements:

1. One update, exactly: a batch of a real rollout (S levels, random initial weights, 64 x 64 steps) goes through
   the compact wire in float32 and in float16, and the learner's PPO update (`learner.update.ppo_update`) runs on
   each from the same parameters and key. Reported: the loss terms of both and the largest parameter difference
   after the update, against the size of the update itself.
2. A short training curve: `impulse launch` of `configs/quick-launch.toml` (learner + 2 actors over Zenoh, the
   compact wire) with float16 features and without, the same seeds, each scored at the end (`eval.json`). A
   distributed run is not bit-reproducible (batches race the weights), so the two modes are compared as
   distributions over seeds, not run by run.

Output: JSON lines on stdout (`record` = "config", "update" for part 1, "run" per launch, "summary" per mode),
progress on stderr.

    impulse bench wire_float16 --seeds 0 1
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from impulse.benchmarks._harness import REPO, emit, environment, progress

QUICK_LAUNCH = REPO / "configs" / "quick-launch.toml"
MODES = {"float32": [], "float16": ["bus.wire_float16=true"]}


def one_update() -> dict[str, Any]:
    """Part 1 (see the module docstring)."""
    from impulse.actors.wire import TrajectoryWire
    from impulse.benchmarks.distributed import rollout_batch
    from impulse.bus.codec import Kind, decode, encode
    from impulse.engine.pytree import tree_arrays
    from impulse.learner.agent import make_agent
    from impulse.learner.config import NetworkConfig, PPOConfig
    from impulse.learner.update import TrainState, make_optimizer, ppo_update

    spec, batch = rollout_batch("s", "entity", num_envs=64, num_steps=64)
    agent = make_agent(NetworkConfig(kind="entity", width=64, depth=2), spec)
    config = PPOConfig(num_envs=64, num_steps=64, num_minibatches=4, update_epochs=4, learning_rate=3e-4,
                       anneal_lr=False)
    optimizer = make_optimizer(config, 1)
    params = agent.init(jax.random.PRNGKey(0))
    state = TrainState(params, optimizer.init(params), np.int32(1))
    update = jax.jit(lambda s, b: ppo_update(s, b, jax.random.PRNGKey(3), apply_fn=agent.apply,
                                             distribution=agent.distribution, optimizer=optimizer, config=config))
    results = {}
    for mode, float16 in (("float32", False), ("float16", True)):
        wire = TrajectoryWire(batch, spec.sizes, compact=True, float16=float16)
        frame = encode(Kind.TRAJECTORY, wire.pack(tree_arrays(batch)), run="bench", meta={"format": wire.format})
        received = wire.checked(decode(bytes(frame), run="bench"))
        new_state, metrics = update(state, received)
        results[mode] = (received, new_state.params, {k: float(v) for k, v in metrics.items()})
    (sent32, params32, metrics32), (sent16, params16, metrics16) = results["float32"], results["float16"]
    leaves = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])  # noqa: E731
    step = np.abs(leaves(params32) - leaves(params)).max()
    apart = np.abs(leaves(params16) - leaves(params32)).max()
    obs_error = max(float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).max())
                    for a, b in zip(jax.tree.leaves(sent32.steps.obs), jax.tree.leaves(sent16.steps.obs), strict=True))
    return {"record": "update", "loss_float32": metrics32["total_loss"], "loss_float16": metrics16["total_loss"],
            "policy_loss_float32": metrics32["policy_loss"], "policy_loss_float16": metrics16["policy_loss"],
            "value_loss_float32": metrics32["value_loss"], "value_loss_float16": metrics16["value_loss"],
            "max_obs_rounding": obs_error, "max_param_change_of_update": float(step),
            "max_param_difference_float16_vs_float32": float(apart)}


def launch(mode: str, seed: int, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    run_dir = work / f"{mode}-{seed}"
    command = [sys.executable, "-m", "impulse.deploy.cli", "launch", "--config", str(QUICK_LAUNCH), f"seed={seed}",
               f"run_dir={run_dir}", f"name=f16-{mode}-{seed}-{os.getpid()}", f"bus.hub=tcp/127.0.0.1:{args.port}",
               f"total_env_steps={args.updates * 64 * 64}", "bus.wire_compact=true", *MODES[mode]]
    started = time.perf_counter()
    with (work / f"{mode}-{seed}.log").open("wb") as out:
        done = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, cwd=REPO, timeout=args.timeout)
    if done.returncode != 0:
        raise RuntimeError(f"launch {mode} seed {seed} failed ({done.returncode}); see {work / f'{mode}-{seed}.log'}")
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    [score] = json.loads((run_dir / "eval.json").read_text()).values()
    solve = [row.get("solve_rate") for row in rows]
    first90 = next((row["update"] for row in rows if (row.get("solve_rate") or 0) >= 0.9), None)
    return {"record": "run", "mode": mode, "seed": seed, "final_solve_rate": score["solve_rate"],
            "updates_to_90": first90, "solve_rate": solve, "total_loss": [row.get("total_loss") for row in rows],
            "seconds": round(time.perf_counter() - started, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench wire_float16", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--updates", type=int, default=30, help="updates of each launch (default 30)")
    parser.add_argument("--port", type=int, default=7641)
    parser.add_argument("--timeout", type=float, default=1200)
    parser.add_argument("--skip-launches", action="store_true", help="part 1 only")
    args = parser.parse_args(argv)
    emit({"record": "config", "seeds": args.seeds, "updates": args.updates, **environment()})
    progress("one update on a float32 and a float16 frame of the same batch ...")
    emit(one_update())
    if args.skip_launches:
        return 0
    runs: dict[str, list[dict[str, Any]]] = {mode: [] for mode in MODES}
    with tempfile.TemporaryDirectory(prefix="wire-f16-") as scratch:
        for seed in args.seeds:
            for mode in MODES:
                progress(f"launch, {mode} features, seed {seed} ...")
                run = launch(mode, seed, args, Path(scratch))
                progress(f"  final solve rate {run['final_solve_rate']:.0%}, 90% at update {run['updates_to_90']}")
                runs[mode].append(run)
                emit(run)
    for mode, done in runs.items():
        finals = [run["final_solve_rate"] for run in done]
        reached = [run["updates_to_90"] for run in done if run["updates_to_90"] is not None]
        emit({"record": "summary", "mode": mode, "seeds": len(done), "final_solve_rate_mean": statistics.fmean(finals),
              "updates_to_90": reached, "seconds_mean": statistics.fmean(run["seconds"] for run in done)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
