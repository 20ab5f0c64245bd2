"""Level generation and mutation throughput: random levels sampled per second, ACCEL mutations (5 edits) per
second, and the compile time of each program, for sizes S, M and L.

Prints JSON lines, one per (task, size, num_levels). Compile time is trace + XLA compile of the batched program
(`jit(...).lower(...).compile()`), measured separately from the timed runs; runs follow the shared harness (two
warm-up calls, median of repeats). No reference system runs here: Kinetix's own figure for its generator is
0.86 M levels/s for S on an H100 at 4,096 levels per batch (see the Kinetix digest, section 9.4).

    impulse bench levels                          # S, M, L; 1,024 levels (CPU) or 4,096 and 65,536 (GPU)
    impulse bench levels --quick                  # S only, 256 levels
    impulse bench levels --sizes l --num-levels 4096 --tasks generate
"""

from __future__ import annotations

import argparse
import time

import jax

from impulse.benchmarks._harness import emit, environment, progress, time_jitted
from impulse.engine.levels.generator import sample_random_level
from impulse.engine.levels.mutations import MutationConfig, mutate_level
from impulse.engine.physics.sizes import size_preset


def _compile(fn, *args):
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    return compiled, time.perf_counter() - start


def measure_generate(size: str, num_levels: int, repeats: int) -> dict:
    sizes = size_preset(size)

    def sample(key):
        return jax.vmap(lambda k: sample_random_level(k, sizes))(jax.random.split(key, num_levels))

    key = jax.random.key(0)
    compiled, compile_s = _compile(sample, key)
    _, run_s = time_jitted(lambda: compiled(key), repeats)
    return {"levels_per_s": num_levels / run_s, "compile_s": compile_s}


def measure_mutate(size: str, num_levels: int, repeats: int, num_edits: int) -> dict:
    sizes = size_preset(size)
    config = MutationConfig(num_edits=num_edits)
    levels = jax.jit(lambda key: jax.vmap(lambda k: sample_random_level(k, sizes))(jax.random.split(key, num_levels)))(
        jax.random.key(1)
    )

    def mutate(key, batch):
        keys = jax.random.split(key, num_levels)
        return jax.vmap(lambda k, lv: mutate_level(k, lv, sizes, config))(keys, batch)

    key = jax.random.key(0)
    compiled, compile_s = _compile(mutate, key, levels)
    _, run_s = time_jitted(lambda: compiled(key, levels), repeats)
    return {"levels_per_s": num_levels / run_s, "compile_s": compile_s, "num_edits": num_edits}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench levels", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="s,m,l", help="comma-separated sizes among s,m,l")
    parser.add_argument("--num-levels", default=None, help="comma-separated batch sizes")
    parser.add_argument("--tasks", default="generate,mutate", help="comma-separated among generate,mutate")
    parser.add_argument("--num-edits", type=int, default=5, help="edits per mutation (ACCEL's default 5)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="S only, 256 levels")
    args = parser.parse_args(argv)

    on_gpu = jax.default_backend() == "gpu"
    if args.quick:
        args.sizes, default_counts = "s", "256"
    else:
        default_counts = "4096,65536" if on_gpu else "1024"
    counts = [int(n) for n in (args.num_levels or default_counts).split(",")]
    env_info = environment()
    for size in args.sizes.split(","):
        for task in args.tasks.split(","):
            for num_levels in counts:
                progress(f"levels: {task}, size {size}, {num_levels} levels ...")
                if task == "generate":
                    result = measure_generate(size, num_levels, args.repeats)
                elif task == "mutate":
                    result = measure_mutate(size, num_levels, args.repeats, args.num_edits)
                else:
                    raise SystemExit(f"unknown task {task!r}; choose among generate, mutate")
                emit({"system": "impulse", "task": task, "size": size, "num_levels": num_levels, **result,
                      **env_info})


if __name__ == "__main__":
    main()
