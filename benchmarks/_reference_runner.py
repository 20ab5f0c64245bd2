"""Measurements of the reference systems (Jax2D 1.0.2, Kinetix 3.0.2), run INSIDE the reference virtualenv.

Why a separate script: Kinetix and Jax2D pin an old JAX, so they live in their own venv (built by
``benchmarks/reference_env.py`` with our JAX version) and this file is the only code that imports them. It
imports nothing from our project except ``scripted_actions.py``, loaded by file path from beside this file, so
the two engines are fed the identical action sequence. Every subcommand prints JSON lines on stdout (progress
goes to stderr); ``reference_env.run_reference`` parses them.

    engine-speed --level PATH --num-envs N --steps T [--repeats 3]
        Jax2D's PhysicsEngine.step, vmapped over N copies of the level, scanned over T steps, constant actions
        of ones; the timing protocol matches benchmarks/_harness.time_jitted.
    trajectory --level PATH [--steps 120] [--actions zero|scripted] [--record 30,60,120]
        One env, jitted single engine steps (no Kinetix frame_skip); body states at the recorded steps.
    trajectories --levels PATH [PATH ...] [--steps 120] [--actions zero|scripted]
        Many levels in one process (for benchmarks/compat_jax2d.py): per level, one jitted scan of Jax2D's
        single-env step over the whole action sequence, compiled once per StaticSimParams (once per size), and
        one JSON line with the initial body flags and every step's body positions.
    env-speed --level PATH --num-envs N --steps T [--repeats 3]
        The Kinetix env (entity observation, multi-discrete actions, auto-reset to the same level, frame_skip
        from the file), vmapped and scanned, uniform random actions drawn inside the scan from a fixed key.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax2d.engine import PhysicsEngine
from jax2d.sim_state import SimParams, SimState, StaticSimParams
from kinetix.environment import make_kinetix_env
from kinetix.environment.spaces import ActionType, ObservationType
from kinetix.util.saving import load_from_json_file

sys.path.append(str(Path(__file__).resolve().parent))  # see _reference_common.py
from _reference_common import action_sequence, as_base, emit, environment, level_name, progress, scripted_actions  # noqa: E402


def load_sim(path: str) -> tuple[SimState, SimParams, StaticSimParams]:
    """Kinetix's JSON loader (kinetix.util.saving.load_from_json_file), reduced to Jax2D's types."""
    env_state, static_env_params, env_params = load_from_json_file(str(Path(path).resolve()))
    return (
        as_base(env_state, SimState),
        as_base(env_params, SimParams),
        as_base(static_env_params, StaticSimParams),
    )


def time_jitted(fn: Callable[[], Any], repeats: int) -> dict[str, float]:
    """Timing record: ``compile_s`` is the two warm-up calls together (the state's weak types change after the
    first call, so the second call compiles again), also given separately as ``warmup1_s``/``warmup2_s``;
    ``run_s`` is the median of ``repeats`` timed calls."""
    warmups = []
    for _ in range(2):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        warmups.append(time.perf_counter() - start)
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return {"compile_s": sum(warmups), "warmup1_s": warmups[0], "warmup2_s": warmups[1],
            "run_s": float(np.median(runs))}


def broadcast(tree: Any, n: int) -> Any:
    return jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x), (n, *jnp.shape(x))), tree)


def engine_speed(args: argparse.Namespace) -> None:
    state, params, static = load_sim(args.level)
    engine = PhysicsEngine(static)
    n, t = args.num_envs, args.steps
    batch = broadcast(state, n)
    actions = jnp.ones((n, static.num_joints + static.num_thrusters), jnp.float32)
    step_batch = jax.vmap(lambda s, a: engine.step(s, params, a)[0])

    @jax.jit
    def rollout(states: SimState) -> SimState:
        return jax.lax.scan(lambda s, _: (step_batch(s, actions), None), states, None, length=t)[0]

    holder = {"state": batch}

    def call() -> SimState:
        # Feed each call's output to the next, as a training loop would (this is what exposes the weak-type
        # recompile on the second call).
        holder["state"] = rollout(holder["state"])
        return holder["state"]

    progress(f"jax2d engine-speed {level_name(args.level)}: {n} envs x {t} steps")
    timing = time_jitted(call, args.repeats)
    emit({"system": "jax2d", "level": level_name(args.level), "num_envs": n, "steps": t,
          "steps_per_s": n * t / timing["run_s"], **timing, "repeats": args.repeats, **environment()})


def _bodies(state: SimState) -> dict[str, list]:
    """Body fields in global-index order (polygons, then circles), as plain lists."""
    def cat(field: str) -> list:
        parts = [np.asarray(getattr(state.polygon, field)), np.asarray(getattr(state.circle, field))]
        return np.concatenate(parts).tolist()

    return {field: cat(field) for field in
            ("position", "rotation", "velocity", "angular_velocity", "active", "inverse_mass")}


def trajectory(args: argparse.Namespace) -> None:
    state, params, static = load_sim(args.level)
    engine = PhysicsEngine(static)
    step = jax.jit(lambda s, a: engine.step(s, params, a)[0])
    record_at = sorted({int(x) for x in args.record.split(",") if x.strip()})
    if record_at and (record_at[0] < 0 or record_at[-1] > args.steps):
        raise SystemExit(f"--record steps must lie in [0, {args.steps}]")
    scripted = scripted_actions() if args.actions == "scripted" else None
    num_joints, num_thrusters = static.num_joints, static.num_thrusters
    frames = [{"step": 0, **_bodies(state)}] if 0 in record_at else []
    progress(f"jax2d trajectory {level_name(args.level)}: {args.steps} steps, {args.actions} actions")
    for i in range(args.steps):
        if scripted is not None:
            action = jnp.asarray(scripted.engine_actions(i, num_joints, num_thrusters))
        else:
            action = jnp.zeros(num_joints + num_thrusters, jnp.float32)
        state = step(state, action)
        if i + 1 in record_at:
            frames.append({"step": i + 1, **_bodies(state)})
    emit({"system": "jax2d", "kind": "trajectory", "level": level_name(args.level), "actions": args.actions,
          "steps": args.steps, "num_polygons": static.num_polygons, "num_circles": static.num_circles,
          "num_joints": num_joints, "num_thrusters": num_thrusters, "frames": frames, **environment()})


def trajectories(args: argparse.Namespace) -> None:
    """Body positions after every step, for many levels, with one compile per static configuration.

    The jitted rollout is cached by StaticSimParams (the only static input; levels of one size share it) and
    takes the state, SimParams and actions as traced arguments, so a new level of an already seen size does not
    recompile. ``traces`` in each record counts the compilations so far."""
    rollouts: dict[str, Callable] = {}
    traces = {"count": 0}

    def make_rollout(static: StaticSimParams) -> Callable:
        engine = PhysicsEngine(static)

        def body(state: SimState, params: SimParams, action: jax.Array) -> tuple[SimState, jax.Array]:
            state = engine.step(state, params, action)[0]
            return state, jnp.concatenate([state.polygon.position, state.circle.position])

        @jax.jit
        def rollout(state: SimState, params: SimParams, actions: jax.Array) -> jax.Array:
            traces["count"] += 1  # runs at trace time only
            return jax.lax.scan(lambda s, a: body(s, params, a), state, actions)[1]

        return rollout

    for path in args.levels:
        state, params, static = load_sim(path)
        key = repr(static)
        if key not in rollouts:
            rollouts[key] = make_rollout(static)
        num_joints, num_thrusters = static.num_joints, static.num_thrusters
        actions = action_sequence(args.steps, num_joints, num_thrusters, args.actions)
        progress(f"jax2d trajectories {level_name(path)}: {args.steps} steps, {args.actions} actions")
        start = time.perf_counter()
        positions = np.asarray(jax.block_until_ready(rollouts[key](state, params, jnp.asarray(actions))))
        initial = _bodies(state)
        emit({"system": "jax2d", "kind": "trajectories", "level": level_name(path), "actions": args.actions,
              "steps": args.steps, "num_polygons": static.num_polygons, "num_circles": static.num_circles,
              "num_joints": num_joints, "num_thrusters": num_thrusters,
              "initial": {k: initial[k] for k in ("position", "active", "inverse_mass")},
              "positions": positions.tolist(), "seconds": time.perf_counter() - start,
              "traces": traces["count"], **environment()})


def env_speed(args: argparse.Namespace) -> None:
    level, static_env_params, env_params = load_from_json_file(str(Path(args.level).resolve()))
    env = make_kinetix_env(ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_ENTITY, None, env_params,
                           static_env_params)
    action_space = env.action_space(env_params)
    n, t = args.num_envs, args.steps
    key = jax.random.PRNGKey(0)
    _, state = env.reset(key, env_params, override_reset_state=level)
    states = broadcast(state, n)

    def step_one(k: jax.Array, s: Any) -> Any:
        action_key, step_key = jax.random.split(k)
        action = action_space.sample(action_key)
        return env.step(step_key, s, action, env_params, override_reset_state=level)[1]

    step_batch = jax.vmap(step_one)

    @jax.jit
    def rollout(states: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        def body(carry: tuple[Any, jax.Array], _: None) -> tuple[tuple[Any, jax.Array], None]:
            s, k = carry
            k, sub = jax.random.split(k)
            return (step_batch(jax.random.split(sub, n), s), k), None

        return jax.lax.scan(body, (states, key), None, length=t)[0]

    holder = {"carry": (states, jax.random.PRNGKey(1))}

    def call() -> Any:
        holder["carry"] = rollout(*holder["carry"])
        return holder["carry"]

    progress(f"kinetix env-speed {level_name(args.level)}: {n} envs x {t} steps "
             f"(frame_skip {static_env_params.frame_skip})")
    timing = time_jitted(call, args.repeats)
    emit({"system": "kinetix-env", "level": level_name(args.level), "num_envs": n, "steps": t,
          "steps_per_s": n * t / timing["run_s"], **timing, "repeats": args.repeats,
          "frame_skip": static_env_params.frame_skip, "observation": "symbolic_entity",
          "action": "multi_discrete", **environment()})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Jax2D / Kinetix reference measurements")
    commands = parser.add_subparsers(dest="command", required=True)
    for name in ("engine-speed", "env-speed"):
        speed = commands.add_parser(name)
        speed.add_argument("--level", required=True)
        speed.add_argument("--num-envs", type=int, required=True)
        speed.add_argument("--steps", type=int, required=True)
        speed.add_argument("--repeats", type=int, default=3)
    traj = commands.add_parser("trajectory")
    traj.add_argument("--level", required=True)
    traj.add_argument("--steps", type=int, default=120)
    traj.add_argument("--actions", choices=("zero", "scripted"), default="zero")
    traj.add_argument("--record", default="30,60,120", help="comma-separated step counts (0 = initial state)")
    many = commands.add_parser("trajectories")
    many.add_argument("--levels", nargs="+", required=True)
    many.add_argument("--steps", type=int, default=120)
    many.add_argument("--actions", choices=("zero", "scripted"), default="zero")
    args = parser.parse_args(argv)
    commands_by_name = {"engine-speed": engine_speed, "trajectory": trajectory, "trajectories": trajectories,
                        "env-speed": env_speed}
    commands_by_name[args.command](args)


if __name__ == "__main__":
    main()
