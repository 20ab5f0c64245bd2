"""Environment throughput: our env step against Kinetix 3.0.2's, in the same run, on the shared Kinetix levels.

What is timed (both sides): a jitted `lax.scan` of the vmapped env step, entity observation, multi-discrete actions
drawn uniformly at random inside the scan, frame skip 2, auto-reset. Ours auto-resets from a level batch (all
shared levels of the size, environment i starting at level i); Kinetix replays its start level through
`override_reset_state` (its cheapest reset path; it computes the reset state every step either way). Neither
environment's cost depends on which level it plays: shapes are fixed per size and there is no data-dependent
control flow. Kinetix runs in its own virtualenv (benchmarks/reference_env.py) with this interpreter's JAX.

Prints JSON lines: one per (system, size, num_envs) with env steps/s and compile time (the two warm-up calls
together), then one ratio line per (size, num_envs).

    impulse bench env                          # S, M, L at 1,024 envs, with Kinetix
    impulse bench env --quick                  # ours only, 256 envs, 16 steps: a smoke run
    impulse bench env --sizes s --num-envs 4096 --no-reference
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from impulse.benchmarks._harness import DEFAULT_LEVELS, emit, environment, progress, require_levels, time_jitted
from impulse.engine.env import env
from impulse.engine.env.actions import action_space
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.levels.level import stack_levels
from impulse.engine.physics.sizes import size_preset


def reward_total(obs: Any, reward: jax.Array) -> jax.Array:
    """What the timed rollout keeps of each step by default: the reward (the observation is left unused, so XLA
    may skip it, as it may on Kinetix's side of the comparison, which discards it too)."""
    del obs
    return reward.sum()


def measure_ours(size: str, num_envs: int, num_steps: int, repeats: int, observation: str = "entity",
                 pixel_downscale: int = 4, keep: Callable[[Any, jax.Array], jax.Array] = reward_total) -> dict:
    """Env steps/s of a scan of vmapped env steps with random multi-discrete actions on every shared level of
    `size`; `keep(obs, reward)` is what each step must produce, which decides what XLA cannot skip."""
    sizes = size_preset(size)
    paths = sorted((require_levels() / size).glob("*.json"))
    levels = stack_levels([load_kinetix_level(path, sizes).level for path in paths])
    spec = EnvSpec(sizes=sizes, observation=observation, action="multi_discrete", pixel_downscale=pixel_downscale)
    params = EnvParams()
    nvec = jnp.asarray(action_space(spec).nvec, jnp.int32)
    step_batch = jax.vmap(env.step, in_axes=(None, None, 0, 0, None))

    @jax.jit
    def rollout(state, key):
        def body(carry, _):
            state, key = carry
            key, sub = jax.random.split(key)
            actions = jax.random.randint(sub, (num_envs, nvec.shape[0]), 0, nvec, jnp.int32)
            obs, state, reward, _, _ = step_batch(spec, params, state, actions, levels)
            return (state, key), keep(obs, reward)

        return jax.lax.scan(body, (state, key), None, length=num_steps)[0]

    _, state = env.reset_batch(spec, params, levels, num_envs)
    holder = {"carry": (state, jax.random.PRNGKey(0))}

    def call():
        # Each call continues from the last one's state, as training does.
        holder["carry"] = rollout(*holder["carry"])
        return holder["carry"]

    compile_s, run_s = time_jitted(call, repeats)
    return {"steps_per_s": num_envs * num_steps / run_s, "compile_s": compile_s, "levels": len(paths)}


def measure_reference(size: str, num_envs: int, num_steps: int, repeats: int) -> dict:
    from impulse.benchmarks.reference_env import ReferenceEnvError, run_reference

    level = str(require_levels() / DEFAULT_LEVELS[size])
    args = ["env-speed", "--level", level, "--num-envs", str(num_envs), "--steps", str(num_steps),
            "--repeats", str(repeats)]
    try:
        records = [r for r in run_reference(args, timeout=3600) if r.get("system") == "kinetix-env"]
    except ReferenceEnvError as error:
        return {"system": "kinetix-env", "error": str(error).splitlines()[0]}
    if len(records) != 1:
        return {"system": "kinetix-env", "error": f"expected one kinetix-env record, got {len(records)}"}
    return records[0]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench env", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="s,m,l", help="comma-separated sizes among s,m,l")
    parser.add_argument("--num-envs", default="1024", help="comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=32, help="env steps per timed scan")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-reference", action="store_true", help="skip Kinetix")
    parser.add_argument("--quick", action="store_true", help="ours only, 256 envs, 16 steps")
    args = parser.parse_args(argv)

    if args.quick:
        args.no_reference, args.steps, args.num_envs = True, 16, "256"
    env_counts = [int(n) for n in args.num_envs.split(",")]
    require_levels()
    env_info = environment()
    if not args.no_reference:
        from impulse.benchmarks.reference_env import ensure_reference_env

        ensure_reference_env()
    for size in args.sizes.split(","):
        for num_envs in env_counts:
            progress(f"env: size {size}, {num_envs} envs ...")
            ours = measure_ours(size, num_envs, args.steps, args.repeats)
            emit({"system": "impulse-env", "size": size, "num_envs": num_envs, "steps": args.steps,
                  "observation": "entity", "action": "multi_discrete", "frame_skip": 2, **ours, **env_info})
            if args.no_reference:
                continue
            ref = measure_reference(size, num_envs, args.steps, args.repeats)
            emit({**ref, "size": size})
            if "error" in ref:
                continue
            emit({"comparison": "impulse-env/kinetix-env", "size": size, "num_envs": num_envs,
                  "speedup": ours["steps_per_s"] / ref["steps_per_s"],
                  "compile_ratio": ours["compile_s"] / ref["compile_s"], **env_info})


if __name__ == "__main__":
    main()
