"""Kinetix 3.0.2's pixel observation, measured INSIDE the reference virtualenv (for benchmarks/pixels.py).

Why a separate script: Kinetix lives in its own venv (benchmarks/reference_env.py) and only reference-side code
imports it. This file imports nothing from our project except ``scripted_actions.py``, loaded by path, so both
sides feed the identical engine actions. It prints JSON lines on stdout (progress on stderr), the protocol of
``reference_env.run_reference``; images are too large for JSON and go to an ``.npz`` file instead.

    render --levels PATH [PATH ...] --record 0,10,30 --out FILE.npz
        Per level: Kinetix's own JSON loader, Jax2D engine steps on Kinetix's state with the shared scripted
        engine actions (single engine steps, no frame skip, as benchmarks/compat_jax2d.py does), and Kinetix's
        pixel renderer (``make_render_pixels_rl``) at the recorded step counts. The npz holds, per level and
        step, the image and the state the renderer read (body positions and rotations, polygons then circles;
        joint and thruster world positions), so our renderer can also be run on Kinetix's own state.
    env-speed --level PATH --num-envs N --steps T [--repeats 3]
        The Kinetix env with the PIXELS observation (multi-discrete actions, auto-reset to the level), vmapped
        and scanned with uniform random actions drawn inside the scan; same protocol as the entity env-speed of
        _reference_runner.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax2d.engine import PhysicsEngine
from kinetix.environment import make_kinetix_env
from kinetix.environment.spaces import ActionType, ObservationType
from kinetix.render.renderer_pixels import make_render_pixels_rl
from kinetix.util.saving import load_from_json_file

sys.path.append(str(Path(__file__).resolve().parent))  # see _reference_common.py
from _reference_common import emit, environment, level_name, progress, scripted_actions  # noqa: E402


def render(args: argparse.Namespace) -> None:
    actions_module = scripted_actions()
    record_at = sorted({int(x) for x in args.record.split(",") if x.strip()})
    arrays: dict[str, np.ndarray] = {}
    compiled: dict[str, tuple[Any, Any]] = {}  # one engine step and one renderer per static configuration
    for path in args.levels:
        state, static, params = load_from_json_file(str(Path(path).resolve()))
        static = static.replace(downscale=args.downscale)
        cache_key = f"{static!r}/{params.pixels_per_unit}"
        if cache_key not in compiled:
            engine = PhysicsEngine(static)
            compiled[cache_key] = (
                jax.jit(lambda s, p, a, engine=engine: engine.step(s, p, a)[0]),
                jax.jit(make_render_pixels_rl(params, static)),
            )
        engine_step, draw = compiled[cache_key]
        name = level_name(path)
        progress(f"kinetix pixels {name}: steps {record_at}")
        start = time.perf_counter()
        for i in range(record_at[-1] + 1):
            if i in record_at:
                obs = draw(state)
                key = f"{name}@{i}"
                arrays[f"{key}/image"] = np.asarray(obs.image, np.float32)
                arrays[f"{key}/global_info"] = np.asarray(obs.global_info, np.float32)
                arrays[f"{key}/position"] = np.concatenate(
                    [np.asarray(state.polygon.position), np.asarray(state.circle.position)]).astype(np.float32)
                arrays[f"{key}/rotation"] = np.concatenate(
                    [np.asarray(state.polygon.rotation), np.asarray(state.circle.rotation)]).astype(np.float32)
                arrays[f"{key}/joint_position"] = np.asarray(state.joint.global_position, np.float32)
                arrays[f"{key}/thruster_position"] = np.asarray(state.thruster.global_position, np.float32)
            action = actions_module.engine_actions(i, static.num_joints, static.num_thrusters)
            state = engine_step(state, params, jnp.asarray(action))
        emit({"system": "kinetix-pixels", "kind": "render", "level": name, "steps": record_at,
              "downscale": static.downscale, "seconds": time.perf_counter() - start, **environment()})
    np.savez_compressed(args.out, **arrays)


def env_speed(args: argparse.Namespace) -> None:
    level, static, params = load_from_json_file(str(Path(args.level).resolve()))
    static = static.replace(downscale=args.downscale)
    env = make_kinetix_env(ActionType.MULTI_DISCRETE, ObservationType.PIXELS, None, params, static)
    action_space = env.action_space(params)
    n, t = args.num_envs, args.steps
    _, state = env.reset(jax.random.PRNGKey(0), params, override_reset_state=level)
    states = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (n, *jnp.shape(x))), state)

    def step_one(key: jax.Array, s: Any) -> tuple[Any, jax.Array]:
        action_key, step_key = jax.random.split(key)
        obs, s, *_ = env.step(step_key, s, action_space.sample(action_key), params, override_reset_state=level)
        return s, obs.image.sum()

    step_batch = jax.vmap(step_one)

    @jax.jit
    def rollout(states: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        def body(carry: tuple[Any, jax.Array], _: None) -> tuple[tuple[Any, jax.Array], jax.Array]:
            s, k = carry
            k, sub = jax.random.split(k)
            s, checksum = step_batch(jax.random.split(sub, n), s)
            return (s, k), checksum.sum()

        return jax.lax.scan(body, (states, key), None, length=t)[0]

    holder = {"carry": (states, jax.random.PRNGKey(1))}

    def call() -> Any:
        holder["carry"] = rollout(*holder["carry"])
        return holder["carry"]

    progress(f"kinetix pixel env-speed {level_name(args.level)}: {n} envs x {t} steps")
    warmups = []
    for _ in range(2):  # the state's weak types change after the first call, so the second compiles again
        start = time.perf_counter()
        jax.block_until_ready(call())
        warmups.append(time.perf_counter() - start)
    runs = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        jax.block_until_ready(call())
        runs.append(time.perf_counter() - start)
    run_s = float(np.median(runs))
    emit({"system": "kinetix-env", "level": level_name(args.level), "num_envs": n, "steps": t,
          "steps_per_s": n * t / run_s, "compile_s": sum(warmups), "run_s": run_s, "repeats": args.repeats,
          "frame_skip": static.frame_skip, "observation": "pixels", "downscale": static.downscale,
          "action": "multi_discrete", **environment()})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Kinetix pixel observation reference measurements")
    commands = parser.add_subparsers(dest="command", required=True)
    draw = commands.add_parser("render")
    draw.add_argument("--levels", nargs="+", required=True)
    draw.add_argument("--record", default="0,10,30", help="comma-separated engine step counts (0 = the level)")
    draw.add_argument("--out", required=True, help="npz file for the images and states")
    draw.add_argument("--downscale", type=int, default=4)
    speed = commands.add_parser("env-speed")
    speed.add_argument("--level", required=True)
    speed.add_argument("--num-envs", type=int, required=True)
    speed.add_argument("--steps", type=int, required=True)
    speed.add_argument("--repeats", type=int, default=3)
    speed.add_argument("--downscale", type=int, default=4)
    args = parser.parse_args(argv)
    {"render": render, "env-speed": env_speed}[args.command](args)


if __name__ == "__main__":
    main()
