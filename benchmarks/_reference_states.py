"""Jax2D 1.0.2 body states after every step, for diagnosing where and why our engine parts from it; run INSIDE
the reference virtualenv (see benchmarks/reference_env.py), like ``_reference_runner.py``.

Why a second script: the compatibility benchmark needs only positions, but finding the cause of a divergence
needs the whole body state (rotation, velocity, spin) at every step, and a way to run Jax2D with a different
contact batch size. ``--batch-size 1`` gives every contact its own batch: no padding slot then exists, so
Jax2D's padding write that wipes the last pair's accumulated impulse (bug B1 of the digest) cannot happen, and
each iteration is a plain Gauss-Seidel sweep over the touching pairs in Jax2D's pair order. Comparing our
engine with both settings separates that bug and the Jacobi batches from everything else.

    levels --levels PATH [PATH ...] [--steps 120] [--actions zero|scripted] [--batch-size 16]

Prints one JSON line per level: the initial body flags and, for steps 1..steps, position [T, N, 2], rotation
[T, N], velocity [T, N, 2] and angular_velocity [T, N] in global-index order (polygons, then circles).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax2d.engine import PhysicsEngine
from jax2d.sim_state import SimParams, SimState, StaticSimParams
from kinetix.util.saving import load_from_json_file

sys.path.append(str(Path(__file__).resolve().parent))  # see _reference_common.py
from _reference_common import action_sequence, as_base  # noqa: E402

FIELDS = ("position", "rotation", "velocity", "angular_velocity")


def joined(state: SimState, field: str) -> jax.Array:
    return jnp.concatenate([getattr(state.polygon, field), getattr(state.circle, field)])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Jax2D body states after every step")
    commands = parser.add_subparsers(dest="command", required=True)
    levels = commands.add_parser("levels")
    levels.add_argument("--levels", nargs="+", required=True)
    levels.add_argument("--steps", type=int, default=120)
    levels.add_argument("--actions", choices=("zero", "scripted"), default="zero")
    levels.add_argument("--batch-size", type=int, default=16, help="Jax2D's solver_batch_size (its default: 16)")
    args = parser.parse_args(argv)

    compiled: dict[str, Any] = {}
    for path in args.levels:
        env_state, static_env, env_params = load_from_json_file(str(Path(path).resolve()))
        state, params = as_base(env_state, SimState), as_base(env_params, SimParams)
        static = dataclasses.replace(as_base(static_env, StaticSimParams), solver_batch_size=args.batch_size)
        key = repr(static)
        if key not in compiled:
            engine = PhysicsEngine(static)

            def body(s: SimState, a: jax.Array, p: SimParams, engine: PhysicsEngine = engine) -> tuple:
                s = engine.step(s, p, a)[0]
                return s, tuple(joined(s, f) for f in FIELDS)

            compiled[key] = jax.jit(lambda s, p, acts, body=body: jax.lax.scan(lambda c, a: body(c, a, p), s, acts)[1])
        actions = action_sequence(args.steps, static.num_joints, static.num_thrusters, args.actions)
        print(f"[reference-states] {path}: {args.steps} steps, {args.actions}, batch {args.batch_size}",
              file=sys.stderr, flush=True)
        values = jax.block_until_ready(compiled[key](state, params, jnp.asarray(actions)))
        record = {
            "system": "jax2d", "kind": "states", "level": f"{Path(path).parent.name}/{Path(path).name}",
            "actions": args.actions, "steps": args.steps, "batch_size": args.batch_size,
            "initial": {f: np.asarray(joined(state, f)).tolist() for f in ("active", "inverse_mass")},
            **{f: np.asarray(v).tolist() for f, v in zip(FIELDS, values, strict=True)},
            "jax_version": jax.__version__,
        }
        print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
