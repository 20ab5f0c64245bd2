"""The fused solver kernel (`SolverOptions.backend="pallas"`) against the XLA step: same levels, same actions, how far
apart the trajectories end.

For each size: every shared Kinetix level of that size and `--random` levels from our generator, `--steps` steps of
random actions (fixed seed) through `vmap(step)` with each backend. Prints one JSON line per size and level
source: the largest body-position difference at the last step and over the run, the median and the 99th
percentile over levels, and how many levels end within `--tolerance` metres. On a GPU the kernel is compiled by
Triton; elsewhere it runs through Pallas's interpreter (`pallas_interpret`), which is slow, so keep the batch small.

    impulse bench kernel_check                                   # S, M, L: shared levels + 1,000 random each
    impulse bench kernel_check --sizes s --random 16 --steps 60  # a CPU-sized check (interpreter)
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from impulse.benchmarks._harness import emit, environment, progress, require_levels
from impulse.engine.levels.generator import sample_random_levels
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SceneSizes, size_preset
from impulse.engine.physics.state import SimState
from impulse.engine.physics.step import step

TOLERANCE_M = 1e-3


def kernel_backend() -> str:
    """The backend that runs the kernel here: compiled on a GPU, interpreted elsewhere."""
    return "pallas" if jax.default_backend() == "gpu" else "pallas_interpret"


@functools.partial(jax.jit, static_argnames=("sizes", "options"))
def trajectories(
    states: SimState, params: SimParams, actions: jax.Array, sizes: SceneSizes, options: SolverOptions
) -> jax.Array:
    """Body positions after every step [T, levels, N, 2] of a batch of scenes under per-step actions [T, levels, A]."""

    def one_step(s: SimState, a: jax.Array):
        s = jax.vmap(lambda scene, act: step(scene, params, act, sizes, options)[0])(s, a)
        return s, s.bodies.position

    return jax.lax.scan(one_step, states, actions)[1]


def compare(states: SimState, params: SimParams, sizes: SceneSizes, num_steps: int, seed: int = 0) -> dict:
    """Run the XLA step and the kernel on the same scenes and actions; the figures described in the docstring."""
    num_levels = states.bodies.position.shape[0]
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, (num_steps, num_levels, sizes.num_joints + sizes.num_thrusters))
    actions = jnp.asarray(actions.astype(np.float32))
    backend = kernel_backend()
    started = time.perf_counter()
    reference = np.asarray(trajectories(states, params, actions, sizes, SolverOptions(backend="xla")))
    fused = np.asarray(trajectories(states, params, actions, sizes, SolverOptions(backend=backend)))
    apart = np.abs(reference - fused).max(axis=(2, 3))  # [T, levels]
    last = apart[-1]
    return {
        "kernel_backend": backend,
        "levels": num_levels,
        "steps": num_steps,
        "max_apart_last_m": float(last.max()),
        "median_apart_last_m": float(np.median(last)),
        "p99_apart_last_m": float(np.quantile(last, 0.99)),
        "max_apart_any_step_m": float(apart.max()),
        "within_tolerance": int((last <= TOLERANCE_M).sum()),
        "tolerance_m": TOLERANCE_M,
        "finite": bool(np.isfinite(fused).all()),
        "seconds": time.perf_counter() - started,
    }


def shared_levels(size: str) -> tuple[SimState, SimParams, SceneSizes]:
    """Every shared Kinetix level of one size, stacked (they share their size class's slot counts)."""
    levels = [load_kinetix_level(str(path)) for path in sorted((require_levels() / size).glob("*.json"))]
    if not levels:
        raise SystemExit(f"no shared Kinetix levels of size {size}")
    states = jax.tree.map(lambda *leaves: jnp.stack(leaves), *[level.state for level in levels])
    return states, levels[0].params, levels[0].sizes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench kernel_check", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="s,m,l", help="comma-separated sizes among s,m,l")
    parser.add_argument("--random", type=int, default=1000, help="random levels per size (0: shared levels only)")
    parser.add_argument("--steps", type=int, default=120, help="steps per trajectory")
    parser.add_argument("--no-shared", action="store_true", help="random levels only")
    args = parser.parse_args(argv)
    info = environment()
    for size in args.sizes.split(","):
        if not args.no_shared:
            progress(f"kernel_check: shared {size} levels, {args.steps} steps ...")
            states, params, sizes = shared_levels(size)
            emit({"check": "kernel/xla", "size": size, "source": "shared", **compare(states, params, sizes, args.steps),
                  **info})
        if args.random:
            progress(f"kernel_check: {args.random} random {size} levels, {args.steps} steps ...")
            sizes = size_preset(size)
            levels = sample_random_levels(jax.random.key(0), args.random, sizes)
            emit({"check": "kernel/xla", "size": size, "source": "random",
                  **compare(levels.state, SimParams(), sizes, args.steps), **info})


if __name__ == "__main__":
    main()
