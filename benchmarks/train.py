"""Fused training throughput: environment steps consumed per second including the PPO update, for S, M and L,
with the compile time of the training step and the share of time spent in rollout vs update.

The timed program is exactly what `impulse train` runs (`learner.fused.FusedTrainer.iterate`). To split the time,
the rollout and the update are also compiled and timed on their own. Levels: all shared Kinetix levels of the
size (auto-reset walks them), as Kinetix's own PPO benchmark trains on the hand-made levels.

Kinetix's figure for comparison (not re-measured here; it needs a GPU): 94.7k env steps/s end to end on an H100
with its entity network, 2,048 envs, 64 steps, 8 epochs, 32 minibatches on S levels. `--kinetix-settings` uses
those settings (the default network here is Kinetix's default size: the permutation-invariant entity network is
the cheaper `entity` kind; `--network transformer` is the paper's model class).

    impulse bench train --quick                       # S, 64 envs, small: a smoke run on CPU
    impulse bench train --sizes s m l --kinetix-settings
"""

from __future__ import annotations

import argparse
import time
from typing import NamedTuple

import jax

from impulse.actors.rollout import rollout
from impulse.actors.trajectory import make_batch
from impulse.benchmarks._harness import emit, environment, progress, require_levels, time_jitted
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.levels.level import Level, stack_levels
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.sizes import size_preset
from impulse.learner.agent import Agent, make_agent
from impulse.learner.config import NetworkConfig, PPOConfig
from impulse.learner.fused import FusedCarry, FusedTrainer
from impulse.learner.update import ppo_update


class FusedSetup(NamedTuple):
    """A fused trainer on every shared Kinetix level of one size, initialised: what the training benchmarks time."""

    spec: EnvSpec
    agent: Agent
    trainer: FusedTrainer
    levels: Level
    carry: FusedCarry
    num_levels: int


def fused_setup(size: str, ppo: PPOConfig, network: NetworkConfig, physics_backend: str = "xla") -> FusedSetup:
    """Build and initialise the fused trainer `impulse train` would run on the shared levels of `size`."""
    sizes = size_preset(size)
    paths = sorted((require_levels() / size).glob("*.json"))
    levels = stack_levels([load_kinetix_level(path, sizes).level for path in paths])
    spec = EnvSpec(sizes=sizes, solver=SolverOptions(backend=physics_backend),
                   observation="symbolic" if network.kind == "flat" else "entity")
    agent = make_agent(network, spec)
    trainer = FusedTrainer(agent, EnvParams(dense_reward_scale=0.2), ppo, num_updates=1000)
    carry = jax.jit(trainer.init)(jax.random.PRNGKey(0), levels)
    jax.block_until_ready(carry)
    return FusedSetup(spec, agent, trainer, levels, carry, len(paths))


def measure(size: str, ppo: PPOConfig, network: NetworkConfig, repeats: int, physics_backend: str = "xla") -> dict:
    spec, agent, trainer, levels, carry, num_levels = fused_setup(size, ppo, network, physics_backend)

    iterate = jax.jit(trainer.iterate)
    start = time.perf_counter()
    compiled = iterate.lower(carry, levels).compile()
    compile_s = time.perf_counter() - start
    state = {"carry": carry}

    def train_step():
        state["carry"], metrics = compiled(state["carry"], levels)
        return metrics

    _, train_s = time_jitted(train_step, repeats)

    roll = jax.jit(lambda c: rollout(agent.act, c.train.params, spec, trainer.env_params, c.envs, levels,
                                     ppo.num_steps))
    _, rollout_s = time_jitted(lambda: roll(state["carry"]), repeats)
    envs, trajectory, train_mask, _, _ = roll(state["carry"])
    batch = make_batch(trajectory, envs.obs, state["carry"].train.policy_version, train_mask=train_mask)
    update = jax.jit(lambda c, b, k: ppo_update(c.train, b, k, apply_fn=agent.apply,
                                                 distribution=agent.distribution, optimizer=trainer.optimizer,
                                                 config=ppo))
    _, update_s = time_jitted(lambda: update(state["carry"], batch, jax.random.PRNGKey(1)), repeats)

    steps = ppo.num_envs * ppo.num_steps
    return {
        "system": "impulse-fused-ppo",
        "physics_backend": physics_backend,
        "size": size,
        "network": network.kind,
        "parameters": sum(x.size for x in jax.tree.leaves(carry.train.params)),
        "num_envs": ppo.num_envs,
        "num_steps": ppo.num_steps,
        "update_epochs": ppo.update_epochs,
        "num_minibatches": ppo.num_minibatches,
        "env_steps_per_s": steps / train_s,
        "compile_s": compile_s,
        "iteration_s": train_s,
        "rollout_s": rollout_s,
        "update_s": update_s,
        "rollout_share": rollout_s / (rollout_s + update_s),
        "levels": num_levels,
        **environment(),
    }


def add_training_arguments(parser: argparse.ArgumentParser) -> None:
    """The sizes, network and PPO settings the training benchmarks share (read back with `training_settings`)."""
    parser.add_argument("--sizes", nargs="+", default=["s", "m", "l"], choices=["s", "m", "l"])
    parser.add_argument("--network", default="entity", choices=["entity", "transformer", "flat"])
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--num-steps", type=int, default=64)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--minibatches", type=int, default=8)
    parser.add_argument("--kinetix-settings", action="store_true",
                        help="2,048 envs x 64 steps, 8 epochs, 32 minibatches (Kinetix's PPO benchmark)")
    parser.add_argument("--quick", action="store_true", help="S only, 64 envs, 16 steps, 2 epochs")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--physics-backend", default="xla", choices=["xla", "pallas"],
                        help="the physics solver stage: XLA, or the fused Pallas kernel (on a GPU)")


def training_settings(args: argparse.Namespace) -> tuple[list[str], PPOConfig, NetworkConfig]:
    """(sizes, PPO settings, network) from `add_training_arguments`' options; the presets win over the numbers."""
    sizes, num_envs, num_steps, epochs, minibatches = args.sizes, args.num_envs, args.num_steps, args.epochs, \
        args.minibatches
    if args.kinetix_settings:
        num_envs, num_steps, epochs, minibatches = 2048, 64, 8, 32
    if args.quick:
        sizes, num_envs, num_steps, epochs, minibatches = ["s"], 64, 16, 2, 4
    ppo = PPOConfig(num_envs=num_envs, num_steps=num_steps, update_epochs=epochs, num_minibatches=minibatches)
    return sizes, ppo, NetworkConfig(kind=args.network)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_arguments(parser)
    args = parser.parse_args(argv)
    sizes, ppo, network = training_settings(args)
    for size in sizes:
        progress(f"fused PPO, size {size}: compiling and timing ...")
        emit(measure(size, ppo, network, args.repeats, args.physics_backend))


if __name__ == "__main__":
    main()
