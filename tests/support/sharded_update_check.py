"""Run the PPO update on one and on several simulated CPU devices (the counts given as arguments) and print how far
the sharded results are from the single-device one, as JSON lines. A script, not a test module: XLA's simulated
device count is fixed when JAX starts, so `test_sharded_update.py` runs it in a process of its own with
XLA_FLAGS=--xla_force_host_platform_device_count=4."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.actors.trajectory import Trajectory, make_batch
from impulse.engine.env.observations import observation_shape
from impulse.engine.env.spec import EnvSpec
from impulse.learner.agent import make_agent
from impulse.learner.config import NetworkConfig, PPOConfig
from impulse.learner.sharding import DataParallel, learner_devices
from impulse.learner.update import TrainState, make_optimizer, ppo_update

NUM_ENVS, NUM_STEPS = 16, 6


def random_batch(agent, params, seed: int):
    """A [T, E] batch acted by `params` on random flat observations, with random rewards, episode ends and a train
    mask that leaves some steps out."""
    rng = np.random.default_rng(seed)
    obs = jnp.asarray(rng.normal(size=(NUM_STEPS + 1, NUM_ENVS) + observation_shape(agent.spec).shape), jnp.float32)
    keys = jax.random.split(jax.random.key(seed), NUM_STEPS * NUM_ENVS).reshape(NUM_STEPS, NUM_ENVS)
    steps_obs = jax.tree.map(lambda x: x[:NUM_STEPS], obs)
    action, log_prob, value = jax.vmap(jax.vmap(lambda o, k: agent.act(params, o, k)))(steps_obs, keys)
    done = rng.random((NUM_STEPS, NUM_ENVS)) < 0.15
    steps = Trajectory(
        obs=steps_obs,
        action=action,
        log_prob=log_prob + jnp.asarray(rng.normal(0.0, 0.1, log_prob.shape), jnp.float32),  # an older policy acted
        value=value,
        reward=jnp.asarray(rng.normal(size=(NUM_STEPS, NUM_ENVS)), jnp.float32),
        done=jnp.asarray(done),
        solved=jnp.asarray(done & (rng.random(done.shape) < 0.5)),
        truncated=jnp.zeros(done.shape, bool),
        episode_return=jnp.zeros(done.shape, jnp.float32),
        level_id=jnp.zeros((NUM_STEPS, NUM_ENVS, 2), jnp.uint32),
    )
    train_mask = jnp.asarray(rng.random((NUM_STEPS, NUM_ENVS)) < 0.9)
    return make_batch(steps, jax.tree.map(lambda x: x[NUM_STEPS], obs), 3, train_mask=train_mask)


class UpdateCase(NamedTuple):
    """One PPO update to compare: the batch, the starting parameters, the update and a fresh state to start from."""

    params: Any
    batch: Any
    key: jax.Array
    update: Callable[..., Any]
    """(state, batch, key, minibatch_sharding=None) -> (state, metrics)"""
    fresh_state: Callable[[], TrainState]


def update_case() -> UpdateCase:
    """The update both checks compare: a small MLP (short compiles; XLA partitions any network the same way) on a
    random batch of NUM_ENVS x NUM_STEPS."""
    agent = make_agent(NetworkConfig(kind="flat", width=16, depth=2, flat_embedding_size=16),
                       EnvSpec(observation="symbolic"))
    ppo = PPOConfig(num_envs=NUM_ENVS, num_steps=NUM_STEPS, num_minibatches=2, update_epochs=2, learning_rate=3e-4)
    optimizer = make_optimizer(ppo, 10)
    params = jax.device_get(agent.init(jax.random.key(0)))  # on the host: every state below is a fresh copy

    def update(state, batch, key, minibatch_sharding=None):
        return ppo_update(state, batch, key, apply_fn=agent.apply, distribution=agent.distribution,
                          optimizer=optimizer, config=ppo, minibatch_sharding=minibatch_sharding)

    def fresh_state():
        return TrainState(params, optimizer.init(params), jnp.asarray(3, jnp.int32))

    return UpdateCase(params, random_batch(agent, params, seed=1), jax.random.key(5), update, fresh_state)


def main() -> None:
    counts = [int(arg) for arg in sys.argv[1:]]
    params, batch, key, update, fresh_state = update_case()
    reference, reference_metrics = jax.device_get(jax.jit(update)(fresh_state(), batch, key))
    moved = max(float(np.max(np.abs(a - b))) for a, b in zip(jax.tree.leaves(reference.params),
                                                              jax.tree.leaves(params)))
    for count in counts:
        parallel = DataParallel(learner_devices(count))
        sharded_update = parallel.jit_update(
            lambda s, b, k, p=parallel: update(s, b, k, minibatch_sharding=p.minibatches), batch)
        placed = parallel.place_batch(batch)
        shard_envs = sorted({shard.data.shape[1] for shard in placed.train_mask.addressable_shards})
        compiled = sharded_update.lower(parallel.replicate(fresh_state()), placed, key).compile()
        state, metrics = jax.device_get(compiled(parallel.replicate(fresh_state()), placed, key))
        param_error = max(float(np.max(np.abs(a - b))) for a, b in zip(jax.tree.leaves(state.params),
                                                                        jax.tree.leaves(reference.params)))
        metric_error = max(abs(float(metrics[name]) - float(reference_metrics[name])) for name in reference_metrics)
        print(json.dumps({
            "devices": count,
            "visible_devices": len(jax.local_devices()),
            "envs_per_device": shard_envs,
            "all_reduce": "all-reduce" in compiled.as_text(),
            "param_max_abs_error": param_error,
            "metric_max_abs_error": metric_error,
            "params_moved_by_update": moved,
            "version": int(state.policy_version),
        }), flush=True)


if __name__ == "__main__":
    main()
