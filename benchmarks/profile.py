"""Where a training iteration's time goes: the fused trainer's iteration split into its parts, each compiled and
timed on its own over the same environments, plus what the distributed mode adds (copies to and from the device)
and how many XLA kernels the physics and env steps compile to.

Parts, each for one iteration's worth of work (`num_envs` x `num_steps` agent steps):

- `physics`: the engine's sub-steps alone (`frame_skip` per agent step, zero actions);
- `env_step`: the whole env step (physics, reward, auto-reset, observation), one sampled action per env held;
- `observation`: building the observation alone, `num_steps` times;
- `policy`: the network's forward pass and action sampling on the batch, `num_steps` times;
- `rollout`: the real rollout (env steps driven by the policy; what actors run);
- `update`: the PPO update on that rollout's batch;
- `iteration`: the fused program `impulse train` runs (rollout then update, one jit);
- `batch_to_host` / `params_to_device`: the copies an actor makes per batch (trajectory out, weights in).

The parts overlap (`rollout` contains `env_step` and `policy`), so the shares are of `iteration`, and their sum is
not meant to be 1: the gap between `rollout` and `env_step + policy` is the scan and sampling overhead. `fusions`
counts the fusion instructions in the optimised HLO of one physics step and of one env step: on a GPU each is
about one kernel launch, which is what bounds a small scene's step there (docs: the Jax2D digest, section 8).

    impulse bench profile --quick                       # S, 64 envs: a smoke run on CPU
    impulse bench profile --sizes s l --kinetix-settings --trace /tmp/impulse-trace   # on a GPU, with a trace

`--trace DIR` also records one fused iteration with `jax.profiler` into DIR (open it with TensorBoard's profile
plugin or Perfetto) to see individual kernels.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from impulse.actors.rollout import rollout
from impulse.actors.trajectory import make_batch
from impulse.benchmarks._harness import emit, environment, progress, time_jitted
from impulse.benchmarks.train import add_training_arguments, fused_setup, training_settings
from impulse.engine.env.env import step as env_step
from impulse.engine.env.observations import observe
from impulse.engine.physics.step import step as physics_step
from impulse.learner.config import NetworkConfig, PPOConfig
from impulse.learner.update import ppo_update

FUSION = re.compile(r"=\s*\S+\s+fusion\(")


def count_fusions(fn: Callable[..., Any], *args: Any) -> int:
    """Fusion instructions in the optimised HLO of `fn(*args)`: a proxy for kernel launches on a GPU."""
    return len(FUSION.findall(jax.jit(fn).lower(*args).compile().as_text()))


def nbytes(tree: Any) -> int:
    return sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(tree))


def profile(size: str, ppo: PPOConfig, network: NetworkConfig, repeats: int, trace: str | None,
            physics_backend: str = "xla") -> dict:
    spec, agent, trainer, levels, carry, num_levels = fused_setup(size, ppo, network, physics_backend)
    envs, params, env_params = carry.envs, carry.train.params, trainer.env_params
    state = envs.env_state
    sims = state.sim
    num_actions = spec.sizes.num_joints + spec.sizes.num_thrusters
    zero_actuation = jnp.zeros((ppo.num_envs, num_actions), jnp.float32)
    fixed_action = agent.act(params, envs.obs, jax.random.PRNGKey(0))[0]  # one sampled action per env, held
    repeated = ppo.num_steps * spec.frame_skip

    def physics_only(sims):
        one = jax.vmap(lambda s, a: physics_step(s, env_params.sim, a, spec.sizes, spec.solver)[0])
        return jax.lax.scan(lambda s, _: (one(s, zero_actuation), None), sims, None, length=repeated)[0]

    def env_only(state):
        one = jax.vmap(lambda s, a: env_step(spec, env_params, s, a, levels)[1])
        return jax.lax.scan(lambda s, _: (one(s, fixed_action), None), state, None, length=ppo.num_steps)[0]

    def observation_only(state):
        def one(total, _):
            obs = jax.vmap(lambda s: observe(spec, s.sim, s.level))(state)
            return total + sum(jnp.sum(x) for x in jax.tree.leaves(obs) if x.dtype != jnp.bool_), None
        return jax.lax.scan(one, jnp.zeros(()), None, length=ppo.num_steps)[0]

    def policy_only(obs, key):
        def one(key, _):
            key, sample_key = jax.random.split(key)
            return key, agent.act(params, obs, sample_key)[0]
        return jax.lax.scan(one, key, None, length=ppo.num_steps)[1]

    roll = jax.jit(lambda c: rollout(agent.act, c.train.params, spec, env_params, c.envs, levels, ppo.num_steps))
    update = jax.jit(lambda c, b, k: ppo_update(c.train, b, k, apply_fn=agent.apply, distribution=agent.distribution,
                                                 optimizer=trainer.optimizer, config=ppo))
    iterate = jax.jit(trainer.iterate)
    physics_fn, env_fn = jax.jit(physics_only), jax.jit(env_only)
    observation_fn, policy_fn = jax.jit(observation_only), jax.jit(policy_only)

    seconds: dict[str, float] = {}
    compile_s: dict[str, float] = {}
    progress(f"profile {size}: physics, env step, observation, policy ...")
    compile_s["physics"], seconds["physics"] = time_jitted(lambda: physics_fn(sims), repeats)
    compile_s["env_step"], seconds["env_step"] = time_jitted(lambda: env_fn(state), repeats)
    compile_s["observation"], seconds["observation"] = time_jitted(lambda: observation_fn(state), repeats)
    compile_s["policy"], seconds["policy"] = time_jitted(lambda: policy_fn(envs.obs, jax.random.PRNGKey(1)),
                                                         repeats)
    progress(f"profile {size}: rollout, update, fused iteration ...")
    compile_s["rollout"], seconds["rollout"] = time_jitted(lambda: roll(carry), repeats)
    rolled = roll(carry)
    batch = make_batch(rolled.steps, rolled.carry.obs, carry.train.policy_version, train_mask=rolled.train_mask)
    compile_s["update"], seconds["update"] = time_jitted(lambda: update(carry, batch, jax.random.PRNGKey(2)),
                                                         repeats)
    compile_s["iteration"], seconds["iteration"] = time_jitted(lambda: iterate(carry, levels), repeats)
    _, seconds["batch_to_host"] = time_jitted(lambda: jax.device_get(batch), repeats)
    host_params = jax.device_get(params)
    _, seconds["params_to_device"] = time_jitted(lambda: jax.device_put(host_params), repeats)

    if trace:
        progress(f"profile {size}: tracing one fused iteration into {trace}")
        with jax.profiler.trace(trace):
            jax.block_until_ready(iterate(carry, levels))

    one_sim = jax.tree.map(lambda x: x[0], sims)
    one_state = jax.tree.map(lambda x: x[0], state)
    fusions = {
        "physics_step": count_fusions(
            lambda s: physics_step(s, env_params.sim, zero_actuation[0], spec.sizes, spec.solver)[0], one_sim
        ),
        "env_step": count_fusions(lambda s: env_step(spec, env_params, s, fixed_action[0], levels)[1], one_state),
    }
    steps = ppo.num_envs * ppo.num_steps
    return {
        "benchmark": "profile",
        "physics_backend": physics_backend,
        "size": size,
        "network": network.kind,
        "num_envs": ppo.num_envs,
        "num_steps": ppo.num_steps,
        "frame_skip": spec.frame_skip,
        "levels": num_levels,
        "seconds": seconds,
        "share_of_iteration": {part: s / seconds["iteration"] for part, s in seconds.items()},
        "env_steps_per_s": {part: steps / seconds[part] for part in ("env_step", "rollout", "iteration")},
        "compile_s": compile_s,
        "batch_bytes": nbytes(batch),
        "params_bytes": nbytes(params),
        "fusions": fusions,
        **environment(),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench profile", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_arguments(parser)
    parser.add_argument("--trace", metavar="DIR", help="also record one fused iteration with jax.profiler here")
    args = parser.parse_args(argv)
    sizes, ppo, network = training_settings(args)
    for size in sizes:
        emit(profile(size, ppo, network, args.repeats, f"{args.trace}/{size}" if args.trace else None,
                     args.physics_backend))


if __name__ == "__main__":
    main()
