"""Stale data is measured in policy versions and dropped beyond the configured limit."""

from __future__ import annotations

import jax.numpy as jnp
import pytest

from impulse.learner.update import check_policy_lag


def test_lag_is_versions_behind_and_limit_is_inclusive():
    check = check_policy_lag(jnp.array([10, 8, 6, 5]), 10, max_policy_lag=4)
    assert check.lag.tolist() == [0, 2, 4, 5]
    assert check.accepted.tolist() == [True, True, True, False]
    # The same rule on the host, as the learner's intake judges a frame's header: a batch from a newer policy
    # than the learner's is never accepted.
    assert check_policy_lag(6, 10, 4) == (4, True) and check_policy_lag(11, 10, 4) == (-1, False)


def test_the_update_measures_lag_from_the_batch_versions():
    """`ppo_update` reports learner version minus the batch's behaviour version; fused batches carry the
    learner's own version, hence lag 0."""
    import jax

    from impulse.actors.trajectory import Trajectory, make_batch
    from impulse.engine.env.observations import observation_shape
    from impulse.engine.env.spec import EnvSpec
    from impulse.learner.agent import make_agent
    from impulse.learner.config import NetworkConfig, PPOConfig
    from impulse.learner.update import TrainState, make_optimizer, ppo_update

    spec = EnvSpec(observation="symbolic")
    agent = make_agent(NetworkConfig(kind="flat", width=8, depth=1, flat_embedding_size=8), spec)
    config = PPOConfig(num_envs=2, num_steps=3, num_minibatches=1, update_epochs=1)
    params = agent.init(jax.random.key(0))
    optimizer = make_optimizer(config, 10)
    obs = jnp.zeros((3, 2) + observation_shape(spec).shape)
    action, log_prob, value = jax.vmap(lambda o: agent.act(params, o, jax.random.key(1)))(obs)
    zeros = jnp.zeros((3, 2))
    steps = Trajectory(obs, action, log_prob, value, zeros, zeros.astype(bool), zeros.astype(bool),
                       zeros.astype(bool), zeros, jnp.zeros((3, 2, 2), jnp.uint32))
    state = TrainState(params, optimizer.init(params), jnp.asarray(9, jnp.int32))
    update = jax.jit(lambda s, b: ppo_update(s, b, jax.random.key(2), apply_fn=agent.apply,
                                             distribution=agent.distribution, optimizer=optimizer, config=config))
    new_state, metrics = update(state, make_batch(steps, obs[-1], behaviour_version=6))
    assert int(metrics["policy_lag"]) == 3 and int(new_state.policy_version) == 10
    _, metrics = update(state, make_batch(steps, obs[-1], behaviour_version=state.policy_version))
    assert int(metrics["policy_lag"]) == 0


def test_the_clip_centred_on_the_learner():
    """`ppo.proximal = "learner"`: on a batch the learner's own parameters acted, the same update as the classic
    clip up to rounding; on a batch another policy acted, the first minibatch step measures its ratios from the
    learner's policy (all 1: nothing clipped), where the classic clip measures them from the behaviour's."""
    import jax
    import numpy as np

    from impulse.actors.trajectory import Trajectory, make_batch
    from impulse.engine.env.observations import observation_shape
    from impulse.engine.env.spec import EnvSpec
    from impulse.learner.agent import make_agent
    from impulse.learner.config import NetworkConfig, PPOConfig
    from impulse.learner.update import TrainState, make_optimizer, ppo_update

    spec = EnvSpec(observation="symbolic")
    agent = make_agent(NetworkConfig(kind="flat", width=8, depth=1, flat_embedding_size=8), spec)
    obs = jax.random.normal(jax.random.key(3), (4, 2) + observation_shape(spec).shape)
    reward = jax.random.normal(jax.random.key(4), (4, 2))
    learner_params = agent.init(jax.random.key(0))
    leaves, tree = jax.tree.flatten(learner_params)  # another policy: every weight moved by noise of scale 1
    noise = [jax.random.normal(key, leaf.shape) for key, leaf in zip(jax.random.split(jax.random.key(5), len(leaves)),
                                                                      leaves)]
    other_params = jax.tree.unflatten(tree, [leaf + n for leaf, n in zip(leaves, noise)])

    def batch_acted_by(params):
        action, log_prob, value = jax.vmap(lambda o: agent.act(params, o, jax.random.key(1)))(obs)
        no = jnp.zeros((4, 2), bool)
        steps = Trajectory(obs, action, log_prob, value, reward, no, no, no, jnp.zeros((4, 2)),
                           jnp.zeros((4, 2, 2), jnp.uint32))
        return make_batch(steps, obs[-1], behaviour_version=0)

    def update(batch, proximal):
        config = PPOConfig(num_envs=2, num_steps=4, num_minibatches=1, update_epochs=1, proximal=proximal)
        optimizer = make_optimizer(config, 10)
        state = TrainState(learner_params, optimizer.init(learner_params), jnp.asarray(0, jnp.int32))
        return ppo_update(state, batch, jax.random.key(2), apply_fn=agent.apply, distribution=agent.distribution,
                          optimizer=optimizer, config=config)

    on_policy = batch_acted_by(learner_params)
    (classic, _), (centred, _) = update(on_policy, "behaviour"), update(on_policy, "learner")
    for a, b in zip(jax.tree.leaves(classic.params), jax.tree.leaves(centred.params)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    lagging = batch_acted_by(other_params)
    _, classic_metrics = update(lagging, "behaviour")
    _, centred_metrics = update(lagging, "learner")
    assert float(classic_metrics["clip_fraction"]) > 0.2
    assert float(centred_metrics["clip_fraction"]) == 0.0 and float(centred_metrics["approx_kl"]) == 0.0
    # How far off-policy each batch was, measured before the update: none for the learner's own, much for the other.
    _, on_policy_metrics = update(on_policy, "learner")
    assert abs(float(on_policy_metrics["behaviour_kl"])) < 1e-6
    assert float(on_policy_metrics["trace_weight"]) == pytest.approx(1.0, abs=1e-6)
    assert float(centred_metrics["behaviour_kl"]) > 0.05 and float(centred_metrics["trace_weight"]) < 0.9
