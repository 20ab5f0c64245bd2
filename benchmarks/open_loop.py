"""Can a level be solved without looking? Open-loop action plans played from a level's start, to tell a level no
policy can solve in our engine from one that is merely hard to find by exploration.

Three families of plans, each one episode of `max_timesteps` agent steps from the level's start (multi-discrete
actions, so every motor and thruster binding has its own dimension):
- constant: every action of the space, held for the whole episode;
- window: one dimension set to one of its non-zero values during steps [start, start + length), the others at
  rest, for every dimension, value, start in `--window-starts` and length in `--window-lengths`;
- random: uniformly random actions every step (`--random` episodes), the exploration a fresh policy does.

Output: one JSON line per level (`record` = "level") with the episodes and solves of each family, the solve
fraction of random play, and the first solving plans of the constant and window families; progress on stderr.

    impulse bench open_loop --levels kinetix:s
    impulse bench open_loop --levels ../shared/kinetix-levels/s/h9_explode_then_thrust_over.json --random 4096
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from impulse.benchmarks._harness import emit, environment, progress
from impulse.engine.env.api import Env, make_env
from impulse.engine.env.env import reset_from_batch

FIRST_SOLVERS = 5
"""Solving plans listed per family in a level's line."""


@dataclass(frozen=True)
class Plans:
    """Action sequences [N, T, D] of one family, and a readable label per plan."""

    actions: np.ndarray
    labels: list[str]


def constant_plans(nvec: tuple[int, ...], steps: int) -> Plans:
    combos = np.array(list(itertools.product(*(range(n) for n in nvec))), dtype=np.int32)
    return Plans(np.repeat(combos[:, None, :], steps, axis=1), [f"hold {c.tolist()}" for c in combos])


def window_plans(nvec: tuple[int, ...], steps: int, starts: list[int], lengths: list[int]) -> Plans:
    time = np.arange(steps)
    plans, labels = [], []
    for dim, n in enumerate(nvec):
        for value, start, length in itertools.product(range(1, n), starts, lengths):
            plan = np.zeros((steps, len(nvec)), np.int32)
            plan[(time >= start) & (time < start + length), dim] = value
            plans.append(plan)
            labels.append(f"dimension {dim} = {value} during steps [{start}, {start + length})")
    return Plans(np.stack(plans), labels)


def random_plans(nvec: tuple[int, ...], steps: int, count: int, seed: int) -> Plans:
    draws = np.random.default_rng(seed).integers(0, nvec, size=(count, steps, len(nvec)), dtype=np.int32)
    return Plans(draws, [f"random {i}" for i in range(count)])


def player(env: Env) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """`play(level, plans)`: whether each plan's first episode on level `level` of the env's set ends solved
    (bool [N]); the episode ends at its first `done` (what follows belongs to the next one). Jitted once, with
    the level traced, so every level and family of a run shares one compile."""

    def episode(level: jax.Array, plan: jax.Array) -> jax.Array:
        key = jax.random.PRNGKey(0)  # draws only the level of the episode after the one that counts
        _, state = reset_from_batch(env.spec, env.params, env.levels, level)

        def act(carry: tuple[Any, jax.Array, jax.Array], action: jax.Array) -> tuple[Any, None]:
            state, solved, ended = carry
            _, state, _, done, info = env.step(key, state, action)
            return (state, solved | (info["solved"] & ~ended), ended | done), None

        (_, solved, _), _ = jax.lax.scan(act, (state, jnp.bool_(False), jnp.bool_(False)), plan)
        return solved

    return jax.jit(jax.vmap(episode, in_axes=(None, 0)))


def solves(play: Callable[[jax.Array, jax.Array], jax.Array], level: int, plans: np.ndarray,
           batch: int) -> np.ndarray:
    """`play` over `plans` in batches of `batch`, the last one padded to full size so that one compile serves
    all."""
    out = []
    for first in range(0, len(plans), batch):
        part = plans[first:first + batch]
        padded = np.concatenate([part, np.zeros((batch - len(part), *part.shape[1:]), part.dtype)])
        out.append(np.asarray(play(jnp.int32(level), jnp.asarray(padded)))[:len(part)])
    return np.concatenate(out) if out else np.zeros(0, bool)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench open_loop", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--levels", required=True, help="a level set, as env.levels takes it (kinetix:s, a file)")
    parser.add_argument("--size", default="s", choices=("s", "m", "l"))
    parser.add_argument("--random", type=int, default=1024, help="random-play episodes per level")
    parser.add_argument("--window-starts", type=int, nargs="+", default=list(range(0, 128, 4)))
    parser.add_argument("--window-lengths", type=int, nargs="+", default=[2, 4, 8, 16, 32, 64, 128, 256])
    parser.add_argument("--batch", type=int, default=1024, help="episodes played at once")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    env = make_env(levels=args.levels, size=args.size)
    nvec, steps = env.action_space.nvec, env.spec.max_timesteps
    emit({"record": "config", **environment(), "levels": args.levels, "size": args.size, "random": args.random,
          "window_starts": args.window_starts, "window_lengths": args.window_lengths, "seed": args.seed,
          "max_timesteps": steps})
    play = player(env)
    for level, name in enumerate(env.level_names):
        record: dict[str, Any] = {"record": "level", "level": name}
        for family, plans in (("constant", constant_plans(nvec, steps)),
                              ("window", window_plans(nvec, steps, args.window_starts, args.window_lengths)),
                              ("random", random_plans(nvec, steps, args.random, args.seed))):
            solved = solves(play, level, plans.actions, args.batch)
            record[family] = {"episodes": int(len(solved)), "solved": int(solved.sum())}
            if family == "random":
                record["random_solve_fraction"] = float(solved.mean()) if len(solved) else 0.0
            else:
                record[family]["first"] = [plans.labels[i] for i in np.flatnonzero(solved)[:FIRST_SOLVERS]]
        emit(record)
        progress(f"{name}: constant {record['constant']['solved']}/{record['constant']['episodes']}, window "
                 f"{record['window']['solved']}/{record['window']['episodes']}, random "
                 f"{record['random']['solved']}/{record['random']['episodes']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
