"""Cost model of one physics step: each stage of `engine.physics.step.step`, compiled alone, against two ceilings.

For each Kinetix level size (S, M, L) and each stage of the step (gravity, constraint preparation, motors,
thrusters, warm start, the solver iterations, integration, the impulse store and pair read-out) and the whole step,
vmapped over N scenes, prints one JSON line with what the compiled program says of itself and how long it takes:

- `flops`, `bytes_accessed`: XLA's cost analysis of the compiled program (`compiled.cost_analysis()`). XLA counts
  a while loop's body once, whatever its trip count; for the stages that hold the solver loop (`solve`, `step`)
  the figures are scaled to `options.iterations` sweeps (`loop_scaled`): the solve stage is also compiled with 1
  iteration, where XLA removes the loop and counts everything, and the scaled cost adds that program's cost once
  for each sweep the loop counted too few. That program also holds the little work outside the loop (rows split by
  phase, impulses put back in slot order), so the scaled figures are upper bounds. XLA's own unscaled figures are
  kept as `xla_flops` and `xla_bytes_accessed`.
- `fusions`: the number of `fusion` instructions in the optimised HLO text (`compiled.as_text()`), in every
  computation (the entry, loop bodies and conditions), each counted once however often its loop runs: the kernels
  the program is built from, statically. `entry_ops`: the instructions of the ENTRY computation other than
  `parameter`, `constant`, `tuple`, `get-tuple-element` and `bitcast` (which move no data): what runs at the top
  level, a while loop counting as one. `while_loops`: `while` instructions anywhere.
- `compile_s`: lowering plus compiling (with the persistent compilation cache on, a cached program loads faster;
  `compilation_cache` says whether it was on). `time_s`: the median of `--repeats` calls after two warm-up calls,
  each waited for with `block_until_ready` (benchmarks/_harness.py's `time_jitted`).
- `floor_s = max(bytes_accessed / bandwidth, flops / rate)`, `time_over_floor = time_s / floor_s`, and
  `share = time_s / (the whole step's time_s)` (stages compiled apart need not add up to the step, which XLA fuses
  across stage boundaries).

The two ceilings are measured in the same run on the same device and printed as one `ceilings` line: a copy
bandwidth (a jitted `x + 1` over a large float32 array, which XLA must read and write in full: 2 x its bytes per
call) and an arithmetic rate (a jitted float32 matmul, 2 n^3 flops per call). The matmul is the device's best case;
the engine's elementwise code cannot reach it, so `time_over_floor` is an upper bound on how far a stage is from
what the device could do.

Each stage is jitted alone on realistic inputs: the stages are run in the step's order, once, on the level's first
state broadcast to N scenes (with all actions at 1), and each stage's inputs are what the earlier stages returned.
Stage functions are the step's own public ones (`step.apply_gravity`, `step.prepare_constraints`, ...), not copies.

    impulse bench step_cost                          # S, M, L at 1,024 scenes
    impulse bench step_cost --quick                  # S only, 64 scenes, 2 repeats: a smoke run
    impulse bench step_cost --sizes s,m --num-envs 4096 --repeats 10
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from impulse.benchmarks._harness import DEFAULT_LEVELS, emit, environment, progress, require_levels, time_jitted
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.physics.actuators import apply_motors, apply_thrusters
from impulse.engine.physics.context import StepContext
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.step import (
    apply_gravity,
    integrate,
    pair_contacts,
    prepare_constraints,
    solve,
    step,
    store_impulses,
    warm_start_all,
)

STAGES = ("apply_gravity", "prepare_constraints", "apply_motors", "apply_thrusters", "warm_start_all", "solve",
          "integrate", "store_impulses+pair_contacts", "step")
"""The stages reported, in the step's order, then the whole step."""

LOOP_STAGES = ("solve", "step")
"""Stages that hold the solver's iteration loop (once each), whose cost analysis is scaled to its trip count."""

NOT_KERNELS = ("parameter", "constant", "tuple", "get-tuple-element", "bitcast")
"""ENTRY instructions that `entry_ops` leaves out: they name or regroup buffers and move no data."""

_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?[\w.\-]+\s*=\s*.*?\s([a-z][\w\-]*)\(")


def cost(compiled: Any) -> dict[str, float]:
    """flops and bytes accessed from `compiled.cost_analysis()`, which JAX versions return as a dict, a list of
    dicts (one per device program; the first is taken) or None (then both are NaN)."""
    analysis = compiled.cost_analysis()
    if isinstance(analysis, list | tuple):
        analysis = analysis[0] if analysis else None
    if not analysis:
        return {"flops": float("nan"), "bytes_accessed": float("nan")}
    return {"flops": float(analysis.get("flops", 0.0)), "bytes_accessed": float(analysis.get("bytes accessed", 0.0))}


def hlo_counts(text: str) -> dict[str, int]:
    """What `fusions`, `entry_ops` and `while_loops` count (the module docstring) in optimised HLO text."""
    fusions = while_loops = entry_ops = 0
    in_entry = False
    for line in text.splitlines():
        if line.startswith("ENTRY "):
            in_entry = True
            continue
        if in_entry and line.startswith("}"):
            in_entry = False
            continue
        match = _INSTRUCTION.match(line)
        if not match:
            continue
        opcode = match.group(1)
        fusions += opcode == "fusion"
        while_loops += opcode == "while"
        if in_entry and opcode not in NOT_KERNELS:
            entry_ops += 1
    return {"fusions": fusions, "entry_ops": entry_ops, "while_loops": while_loops}


def compile_and_time(fn: Callable[..., Any], args: tuple[Any, ...], repeats: int) -> tuple[Any, dict[str, Any]]:
    """Jit, lower and compile `fn` for `args`; its cost analysis, HLO counts, compile time and median call time;
    returns (its outputs, that record)."""
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - start
    _, time_s = time_jitted(lambda: compiled(*args), repeats)
    record = {**cost(compiled), **hlo_counts(compiled.as_text()), "compile_s": compile_s, "time_s": time_s}
    return compiled(*args), record


def ceilings(repeats: int, copy_elements: int = 1 << 25, matmul_n: int = 2048) -> dict[str, float]:
    """The device's copy bandwidth (bytes/s) and matmul rate (flops/s), measured here, as the floors' divisors."""
    x = jnp.ones((copy_elements,), jnp.float32)
    copy = jax.jit(lambda a: a + 1.0)
    _, copy_s = time_jitted(lambda: copy(x), repeats)
    a = jnp.ones((matmul_n, matmul_n), jnp.float32) * 0.5
    matmul = jax.jit(lambda p, q: p @ q)
    _, matmul_s = time_jitted(lambda: matmul(a, a), repeats)
    return {"bandwidth_bytes_per_s": 2 * x.nbytes / copy_s, "rate_flops_per_s": 2 * matmul_n**3 / matmul_s,
            "copy_bytes": 2 * x.nbytes, "copy_s": copy_s, "matmul_n": matmul_n, "matmul_s": matmul_s}


def _solve_only(iterations: int, context: StepContext) -> Callable[..., Any]:
    """The vmapped solve stage with `iterations` sweeps instead of the level's (for the loop scaling)."""
    options = dataclasses.replace(context.options, iterations=iterations)
    return jax.vmap(lambda start, carried, ctx: solve(start, carried, dataclasses.replace(ctx,
                                                                                                   options=options)))


def measure_level(level_path: str, num_envs: int, repeats: int) -> dict[str, dict[str, Any]]:
    """Every stage's record (`compile_and_time`'s, loop-scaled where needed) for one level at `num_envs` scenes."""
    level = load_kinetix_level(level_path)
    sizes: SceneSizes = level.sizes
    params: SimParams = level.params
    options: SolverOptions = level.options
    state = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_envs,) + x.shape), level.state)
    actions = jnp.ones((num_envs, sizes.num_joints + sizes.num_thrusters), jnp.float32)
    motor_actions, thruster_actions = actions[:, : sizes.num_joints], actions[:, sizes.num_joints :]
    records: dict[str, dict[str, Any]] = {}

    def run(name: str, fn: Callable[..., Any], *args: Any) -> Any:
        progress(f"step_cost: {name} ...")
        out, records[name] = compile_and_time(fn, args, repeats)
        return out

    velocity = run("apply_gravity", jax.vmap(apply_gravity, in_axes=(0, None)), state, params)
    context, carried = run("prepare_constraints", jax.vmap(
        lambda s, v, p: prepare_constraints(s, v, p, sizes, options), in_axes=(0, 0, None)),
        state, velocity, params)
    angular_velocity = run("apply_motors", jax.vmap(
        lambda w, s, rows, a, p: apply_motors(w, s, rows, a, p), in_axes=(0, 0, 0, 0, None)),
        state.bodies.angular_velocity, state, context.joint_rows, motor_actions, params)
    velocity, angular_velocity = run("apply_thrusters", jax.vmap(apply_thrusters, in_axes=(0, 0, 0, 0, None)),
                                     velocity, angular_velocity, state, thruster_actions, params)
    start = run("warm_start_all", jax.vmap(warm_start_all), velocity, angular_velocity, state, carried,
                context)
    solved, impulses = run("solve", jax.vmap(solve), start, carried, context)
    run("integrate", jax.vmap(integrate, in_axes=(0, 0, None)), state, solved, params)

    def store_and_pair(impulses: Any, ctx: StepContext) -> Any:
        cache = store_impulses(impulses, ctx)
        return cache, pair_contacts(cache, ctx)

    run("store_impulses+pair_contacts", jax.vmap(store_and_pair), impulses, context)
    run("step", jax.vmap(lambda s, a, p: step(s, p, a, sizes, options), in_axes=(0, 0, None)),
        state, actions, params)

    # XLA counts the solver loop's body once; at 1 iteration there is no loop, so that program counts one sweep in
    # full (with the little work outside the loop: an upper bound on a sweep).
    iterations = options.iterations
    progress("step_cost: solve at 1 iteration (loop scaling) ...")
    compiled = jax.jit(_solve_only(1, context)).lower(start, carried, context).compile()
    sweep, sweep_loops = cost(compiled), hlo_counts(compiled.as_text())["while_loops"]
    scalable = sweep_loops == 0 and records["solve"]["while_loops"] >= 1
    for name in STAGES:
        record = records[name]
        record["xla_flops"], record["xla_bytes_accessed"] = record["flops"], record["bytes_accessed"]
        record["loop_scaled"] = name in LOOP_STAGES and scalable
        if record["loop_scaled"]:
            for key in ("flops", "bytes_accessed"):
                record[key] = record[key] + (iterations - 1) * sweep[key]
    records["step"]["iterations"] = records["solve"]["iterations"] = iterations
    return records


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench step_cost", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="s,m,l", help="comma-separated sizes among s,m,l")
    parser.add_argument("--num-envs", type=int, default=None, help="scenes per vmapped call (default 1,024)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per stage after warm-up (default 5)")
    parser.add_argument("--quick", action="store_true", help="S only, 64 scenes, 2 repeats: a smoke run")
    args = parser.parse_args(argv)
    if args.quick:
        sizes, num_envs, repeats = ["s"], args.num_envs or 64, args.repeats or 2
    else:
        sizes, num_envs, repeats = [s.strip() for s in args.sizes.split(",") if s.strip()], args.num_envs or 1024, \
            args.repeats or 5
    if not sizes or any(s not in DEFAULT_LEVELS for s in sizes):
        parser.error(f"--sizes: expected some of {','.join(DEFAULT_LEVELS)}, got {args.sizes!r}")
    if num_envs < 1 or repeats < 1:
        parser.error("--num-envs and --repeats must be positive")
    levels_dir = require_levels()
    env_info = environment()
    emit({"record": "environment", **env_info,
          "compilation_cache": bool(jax.config.jax_compilation_cache_dir)})
    progress("step_cost: ceilings ...")
    ceiling = ceilings(max(repeats, 3))
    emit({"record": "ceilings", **ceiling, **env_info})
    bandwidth, rate = ceiling["bandwidth_bytes_per_s"], ceiling["rate_flops_per_s"]
    for size in sizes:
        progress(f"step_cost: size {size}, {num_envs} envs ...")
        records = measure_level(str(levels_dir / DEFAULT_LEVELS[size]), num_envs, repeats)
        step_s = records["step"]["time_s"]
        for name in STAGES:
            record = records[name]
            floor_s = max(record["bytes_accessed"] / bandwidth, record["flops"] / rate)
            emit({"record": "stage", "size": size, "level": DEFAULT_LEVELS[size], "stage": name,
                  "num_envs": num_envs, "repeats": repeats, **record, "floor_s": floor_s,
                  "time_over_floor": record["time_s"] / floor_s if floor_s > 0 else float("inf"),
                  "share": record["time_s"] / step_s, **env_info})


if __name__ == "__main__":
    main()
