"""Engine throughput: our physics step against Jax2D 1.0.2 on the same Kinetix levels, in the same run.

Prints JSON lines: one per (system, size, num_envs) with steps/s and compile time, then one ratio line per
(size, num_envs). Jax2D runs in its own virtualenv (built on first use by benchmarks/reference_env.py, with this
interpreter's JAX version) because Kinetix pins an old JAX.

    impulse bench engine                      # S, M, L at 1 and 1,024 envs (+32,768 on a GPU), with Jax2D
    impulse bench engine --quick              # our engine only, small batches: a smoke run
    impulse bench engine --sizes s --num-envs 4096 --no-reference
    impulse bench engine --quick --solver phased,jax2d   # both contact schedules (SolverOptions.schedule)
    impulse bench engine --backend xla,pallas            # the XLA solver stage and the fused kernel (on a GPU)
"""

from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp

from impulse.benchmarks._harness import DEFAULT_LEVELS, emit, environment, progress, require_levels, time_jitted
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.physics.options import SCHEDULES as SOLVERS
from impulse.engine.physics.step import step


def measure_ours(
    level_path: str, num_envs: int, num_steps: int, repeats: int, solver: str = "phased", backend: str = "xla"
) -> dict:
    level = load_kinetix_level(level_path)
    sizes, params = level.sizes, level.params
    options = dataclasses.replace(level.options, schedule=solver, backend=backend)
    batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (num_envs,) + x.shape), level.state)
    actions = jnp.ones((num_envs, sizes.num_joints + sizes.num_thrusters), jnp.float32)
    step_batch = jax.vmap(lambda s, a: step(s, params, a, sizes, options)[0])

    @jax.jit
    def rollout(state):
        return jax.lax.scan(lambda s, _: (step_batch(s, actions), None), state, None, length=num_steps)[0]

    compile_s, run_s = time_jitted(lambda: rollout(batch), repeats)
    return {"steps_per_s": num_envs * num_steps / run_s, "compile_s": compile_s}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench engine", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="s,m,l", help="comma-separated sizes among s,m,l")
    parser.add_argument("--num-envs", default=None, help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=100, help="engine steps per timed scan")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-reference", action="store_true", help="skip Jax2D")
    parser.add_argument("--quick", action="store_true", help="our engine only, 1 and 256 envs, 50 steps")
    parser.add_argument("--solver", default="phased",
                        help=f"comma-separated among {','.join(SOLVERS)}: our contact schedule(s) (default phased)")
    parser.add_argument("--backend", default="xla",
                        help="comma-separated among xla,pallas: how the phased solver runs (pallas: the fused kernel, "
                        "a GPU only; with --solver phased)")
    args = parser.parse_args(argv)
    solvers = [m.strip() for m in args.solver.split(",") if m.strip()]
    if not solvers or any(m not in SOLVERS for m in solvers):
        parser.error(f"--solver: expected some of {', '.join(SOLVERS)}, got {args.solver!r}")
    backends = [b.strip() for b in args.backend.split(",") if b.strip()]
    if not backends or any(b not in ("xla", "pallas") for b in backends):
        parser.error(f"--backend: expected some of xla,pallas, got {args.backend!r}")
    if "pallas" in backends and (solvers != ["phased"] or jax.default_backend() != "gpu"):
        parser.error("--backend pallas: the fused kernel runs the phased solver, on a GPU")

    on_gpu = jax.default_backend() == "gpu"
    if args.quick:
        args.no_reference, args.steps, default_envs = True, 50, "1,256"
    else:
        default_envs = "1,1024,32768" if on_gpu else "1,1024"
    env_counts = [int(n) for n in (args.num_envs or default_envs).split(",")]
    levels_dir = require_levels()
    env_info = environment()
    reference = None
    if not args.no_reference:
        from impulse.benchmarks.reference_env import ensure_reference_env, run_reference

        ensure_reference_env()
        reference = run_reference
    for size in args.sizes.split(","):
        level = str(levels_dir / DEFAULT_LEVELS[size])
        for num_envs in env_counts:
            progress(f"engine: size {size}, {num_envs} envs ...")
            measured = {}
            for solver in solvers if "xla" in backends else []:
                measured[solver] = measure_ours(level, num_envs, args.steps, args.repeats, solver)
                emit({"system": "impulse", "solver": solver, "size": size, "level": DEFAULT_LEVELS[size],
                      "num_envs": num_envs, "steps": args.steps, **measured[solver], **env_info})
            if "phased" in measured and "jax2d" in measured:
                emit({"comparison": "jax2d/phased", "size": size, "num_envs": num_envs,
                      "speed_ratio": measured["jax2d"]["steps_per_s"] / measured["phased"]["steps_per_s"],
                      **env_info})
            if "pallas" in backends:
                fused = measure_ours(level, num_envs, args.steps, args.repeats, "phased", "pallas")
                emit({"system": "impulse", "solver": "phased", "physics_backend": "pallas", "size": size,
                      "level": DEFAULT_LEVELS[size], "num_envs": num_envs, "steps": args.steps, **fused, **env_info})
                if "xla" in backends:
                    emit({"comparison": "pallas/xla", "size": size, "num_envs": num_envs,
                          "speed_ratio": fused["steps_per_s"] / measured["phased"]["steps_per_s"], **env_info})
                measured["pallas"] = fused
            if reference is None:
                continue
            (ref,) = [
                r for r in reference(
                    ["engine-speed", "--level", level, "--num-envs", str(num_envs), "--steps", str(args.steps),
                     "--repeats", str(args.repeats)],
                    timeout=1800,
                ) if r.get("system") == "jax2d"
            ]
            emit({**ref, "size": size})
            for variant, ours in measured.items():
                emit({"comparison": "impulse/jax2d", "solver": "phased" if variant == "pallas" else variant,
                      "physics_backend": "pallas" if variant == "pallas" else "xla", "size": size,
                      "num_envs": num_envs,
                      "speedup": ours["steps_per_s"] / ref["steps_per_s"],
                      "compile_ratio": ours["compile_s"] / ref["compile_s"], **env_info})


if __name__ == "__main__":
    main()
