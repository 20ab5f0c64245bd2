"""Can a level be solved without looking? Open-loop action plans played from a level's start, to tell a level no
policy can solve in our engine from one that is merely hard to find by exploration.

Three families of plans, each one episode of `max_timesteps` agent steps from the level's start (multi-discrete
actions, so every motor and thruster binding has its own dimension):
- constant: every action of the space, held for the whole episode;
- window: one dimension set to one of its non-zero values during steps [start, start + length), the others at
  rest, for every dimension, value, start in `--window-starts` and length in `--window-lengths`;
- random: uniformly random actions every step (`--random` episodes), the exploration a fresh policy does.

With `--agent RUN_DIR` (a trained policy, such as pretrained/general-s; or one checkpoint, `RUN_DIR/checkpoints/N`),
the levels are played in that run's environment settings, and the agent plays `--agent-episodes` sampled episodes
from each level's start. Its line then says how much probability the agent gives, at each step of its own
episodes, to the actions whose holding solves the level (the constant family's solvers), against the share those
actions have of the action space: whether the agent's moves lean towards a plan that works or away from it.

Output: one JSON line per level (`record` = "level") with the episodes and solves of each family, the solve
fraction of random play, the first solving plans of the constant and window families and, with `--agent`, the
agent's part (`agent`); progress on stderr.

    impulse bench open_loop --levels kinetix:s
    impulse bench open_loop --levels ../shared/kinetix-levels/s/h9_explode_then_thrust_over.json --random 4096
    impulse bench open_loop --levels kinetix:s --agent pretrained/general-s
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.benchmarks._harness import emit, environment, progress
from impulse.engine.env.api import Env, make_env
from impulse.engine.env.env import reset_batch, reset_from_batch
from impulse.engine.env.episodes import LoopCarry, Step, episode_loop, first_episode, first_episode_start
from impulse.learner.agent import Agent, make_agent

FIRST_SOLVERS = 5
"""Solving plans listed per family in a level's line."""
EARLY_STEPS = 16
"""The agent's early moves: its first this many steps (h0 and h1 need the thruster through about 16)."""


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


class AgentEpisodes(NamedTuple):
    """An agent's own sampled episodes, E per level, environment k * E + e playing level k: its action
    distribution's parameters at every step [T, K * E, P], whether the step belongs to the first episode
    [T, K * E], and whether that episode ended solved [K * E]."""

    dist_params: np.ndarray
    live: np.ndarray
    solved: np.ndarray


def load_agent(checkpoint: Path, levels: str, size: str) -> tuple[Env, Agent, Any]:
    """(env over `levels` in size class `size` with the run's other environment settings, the run's `Agent`, its
    policy) of `checkpoint`: a run directory (its newest checkpoint) or one checkpoint's folder, as `impulse eval
    --checkpoint` takes it."""
    from impulse.deploy.config import load_run_config
    from impulse.deploy.run_config import RunConfig
    from impulse.deploy.runtime.run_dirs import locate_checkpoint
    from impulse.learner.run import restore_policy

    run_dir, step = locate_checkpoint(checkpoint)
    config = load_run_config(RunConfig, run_dir)
    settings = {field: value for field, value in dataclasses.asdict(config.env).items()
                if field not in ("levels", "size")}
    env = make_env(levels=levels, size=size, **settings)
    agent = make_agent(config.network, env.spec)
    return env, agent, restore_policy(config, run_dir, step).items["train"].params


def agent_episodes(env: Env, agent: Agent, params: Any, episodes: int, seed: int) -> AgentEpisodes:
    """`episodes` episodes of the agent's sampled policy from the start of each of the env's levels."""
    levels = jax.tree.map(lambda x: jnp.repeat(x, episodes, axis=0), env.levels)
    num_envs = env.num_levels * episodes

    def play(levels: Any, key: jax.Array) -> tuple[Any, Any]:
        obs, state = reset_batch(env.spec, env.params, levels, num_envs)

        def act(obs: Any, state: Any, key: jax.Array) -> tuple[jax.Array, jax.Array]:
            dist_params, _ = agent.apply(params, obs)
            return agent.distribution.sample(dist_params, key), dist_params

        def record(step: Step) -> tuple[jax.Array, jax.Array]:
            return step.aux, ~step.extra.finished

        start = LoopCarry(state, obs, key, first_episode_start(num_envs))
        carry, (dist_params, live) = episode_loop(env.spec, env.params, levels, start, env.spec.max_timesteps, act,
                                                  record, first_episode)
        return (dist_params, live), carry.extra.solved

    (dist_params, live), solved = jax.jit(play)(levels, jax.random.PRNGKey(seed))
    return AgentEpisodes(np.asarray(dist_params), np.asarray(live), np.asarray(solved))


def action_mass(agent: Agent, dist_params: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """The probability the agent's distributions `dist_params` [..., P] give to the set of `actions` [M, D]
    together [...]."""
    batch = dist_params.shape[:-1]
    log_probs = jax.vmap(lambda action: agent.distribution.log_prob(
        jnp.asarray(dist_params), jnp.broadcast_to(action, (*batch, action.shape[-1]))))(jnp.asarray(actions))
    return np.asarray(jnp.exp(jax.nn.logsumexp(log_probs, axis=0)))


def agent_record(agent: Agent, played: AgentEpisodes, level: int, episodes: int, solving: np.ndarray,
                 num_actions: int) -> dict[str, Any]:
    """The agent's part of level `level`'s line: its solve rate over its episodes and, where holding an action
    solves the level, the probability it gives those `solving` actions [M, D] together (mean over the steps of its
    first episodes) at its first step, over its first `EARLY_STEPS` steps and over the whole episode, beside their
    share of the action space (what a uniformly random policy gives them)."""
    envs = slice(level * episodes, (level + 1) * episodes)
    record: dict[str, Any] = {"episodes": episodes, "solve_rate": float(played.solved[envs].mean())}
    if len(solving):
        mass = action_mass(agent, played.dist_params[:, envs], solving)
        live = played.live[:, envs]
        record.update(solving_hold_share=len(solving) / num_actions,
                      solving_hold_mass_first_step=float(mass[0].mean()),
                      solving_hold_mass_early=float(mass[:EARLY_STEPS][live[:EARLY_STEPS]].mean()),
                      solving_hold_mass_episode=float(mass[live].mean()))
    return record


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
    parser.add_argument("--agent", type=Path, help="a run directory (its newest checkpoint) or one checkpoint's "
                        "folder, whose policy also plays each level (its environment settings but --size are used "
                        "for every family)")
    parser.add_argument("--agent-episodes", type=int, default=64, help="the agent's episodes per level")
    args = parser.parse_args(argv)
    if args.agent is not None:
        from impulse.learner.run import RunError

        try:
            env, agent, params = load_agent(args.agent, args.levels, args.size)
        except (FileNotFoundError, RunError) as err:
            parser.error(f"--agent {args.agent}: {err}")
        if env.spec.action != "multi_discrete":
            parser.error(f"--agent {args.agent}: its actions are {env.spec.action}; the plans are multi-discrete")
    else:
        env, agent, params = make_env(levels=args.levels, size=args.size), None, None
    nvec, steps = env.action_space.nvec, env.spec.max_timesteps
    emit({"record": "config", **environment(), "levels": args.levels, "size": args.size, "random": args.random,
          "window_starts": args.window_starts, "window_lengths": args.window_lengths, "seed": args.seed,
          "max_timesteps": steps, "agent": None if args.agent is None else str(args.agent),
          "agent_episodes": args.agent_episodes if args.agent is not None else 0})
    play = player(env)
    if agent is not None:
        played = agent_episodes(env, agent, params, args.agent_episodes, args.seed)
    constant = constant_plans(nvec, steps)
    families = (("constant", constant), ("window", window_plans(nvec, steps, args.window_starts, args.window_lengths)),
                ("random", random_plans(nvec, steps, args.random, args.seed)))  # the same plans on every level
    for level, name in enumerate(env.level_names):
        record: dict[str, Any] = {"record": "level", "level": name}
        for family, plans in families:
            solved = solves(play, level, plans.actions, args.batch)
            record[family] = {"episodes": int(len(solved)), "solved": int(solved.sum())}
            if family == "random":
                record["random_solve_fraction"] = float(solved.mean()) if len(solved) else 0.0
            else:
                record[family]["first"] = [plans.labels[i] for i in np.flatnonzero(solved)[:FIRST_SOLVERS]]
            if family == "constant" and agent is not None:
                record["agent"] = agent_record(agent, played, level, args.agent_episodes,
                                               constant.actions[solved, 0], len(constant.actions))
        emit(record)
        progress(f"{name}: constant {record['constant']['solved']}/{record['constant']['episodes']}, window "
                 f"{record['window']['solved']}/{record['window']['episodes']}, random "
                 f"{record['random']['solved']}/{record['random']['episodes']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
