"""The wire layout of the actor-learner types: a trajectory batch and the weights survive encode/decode exactly,
and the receivers' schemas refuse what does not fit their compiled functions."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from impulse.actors.rollout import rollout, start_rollout
from impulse.actors.trajectory import make_batch
from impulse.actors.wire import checked_tree, trajectory_schema, trajectory_template, weights_hash, weights_schema
from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.schema import check
from impulse.bus.stamp import Stamp
from impulse.bus.weights import decode_weights, encode_weights
from impulse.curriculum.results import level_results
from impulse.curriculum.wire import LEVEL_RESULTS_SCHEMA, results_arrays
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import level_from_scene, stack_levels
from impulse.engine.physics.building import empty_scene
from impulse.engine.pytree import tree_arrays
from impulse.learner.agent import make_agent
from impulse.learner.config import NetworkConfig

RUN = "wire-test"
NETWORK = NetworkConfig(kind="entity", width=16, depth=1, entity_encoder_size=16, entity_heads=2, entity_head_size=8)


def random_like(template, seed: int):
    rng = np.random.default_rng(seed)

    def fill(leaf):
        if leaf.dtype == bool:
            return rng.random(leaf.shape) < 0.3
        if np.issubdtype(leaf.dtype, np.integer):
            return rng.integers(0, 3, leaf.shape).astype(leaf.dtype)
        return rng.standard_normal(leaf.shape).astype(leaf.dtype)

    return jax.tree.map(fill, template)


def traced_batch(spec: EnvSpec, network: NetworkConfig, num_envs: int, num_steps: int):
    """The batch a rollout of `spec` makes, as shapes (traced, never run): what `trajectory_template` writes out."""
    agent = make_agent(network, spec)
    levels = stack_levels([level_from_scene(empty_scene(spec.sizes))])

    def one_batch():
        carry = start_rollout(spec, EnvParams(), levels, num_envs, jax.random.key(0))
        params = agent.init(jax.random.key(0))
        carry, steps, train_mask, episodes, _ = rollout(agent.act, params, spec, EnvParams(), carry, levels,
                                                        num_steps)
        return make_batch(steps, carry.obs, 0, train_mask=train_mask, episodes=episodes)

    return jax.eval_shape(one_batch)


@pytest.mark.parametrize(("observation", "action", "network"), [
    ("entity", "multi_discrete", NETWORK), ("pixels", "continuous", NetworkConfig(kind="cnn")),
    ("symbolic", "discrete", NetworkConfig(kind="flat", width=16, depth=1)),
    ("blind", "multi_discrete", NetworkConfig(kind="flat", width=16, depth=1))])
def test_the_trajectory_template_is_what_a_rollout_makes(observation, action, network):
    spec = dataclasses.replace(EnvSpec(), observation=observation, action=action)
    written, traced = trajectory_template(spec, 3, 2), traced_batch(spec, network, 3, 2)
    assert jax.tree.structure(written) == jax.tree.structure(traced)
    shapes = lambda tree: [(leaf.shape, leaf.dtype) for leaf in jax.tree.leaves(tree)]  # noqa: E731
    assert shapes(written) == shapes(traced)


def test_trajectory_batch_round_trips_bit_for_bit_and_results_by_level_id():
    template = trajectory_template(EnvSpec(), num_envs=4, num_steps=3)
    batch = random_like(template, 0)
    frame = encode(Kind.TRAJECTORY, tree_arrays(batch), run=RUN, seq=1)
    received = checked_tree(decode(bytes(frame), run=RUN, kinds=Kind.TRAJECTORY), trajectory_schema(template),
                            template)
    for sent, got in zip(jax.tree.leaves(batch), jax.tree.leaves(received), strict=True):
        np.testing.assert_array_equal(sent, got)
    steps = batch.steps
    results = level_results(steps.level_id, steps.done, steps.solved, steps.episode_return, steps.value,
                            steps.reward, 0, rows=steps.done.size)
    message = decode(bytes(encode(Kind.LEVEL_RESULTS, results_arrays(results), run=RUN)), run=RUN)
    check(message, LEVEL_RESULTS_SCHEMA)
    assert int(message.arrays["episodes"].sum()) == int(np.asarray(batch.steps.done).sum())

    other = trajectory_template(EnvSpec(), num_envs=5, num_steps=3)  # an actor with another batch shape
    frame = encode(Kind.TRAJECTORY, tree_arrays(random_like(other, 1)), run=RUN)
    with pytest.raises(Rejected) as refused:
        checked_tree(decode(bytes(frame), run=RUN), trajectory_schema(template), template)
    assert refused.value.reason == "bad_shape"


def test_weights_of_another_network_are_refused_by_their_tree_hash():
    params = make_agent(NETWORK, EnvSpec()).init(jax.random.key(0))
    schema = weights_schema(params)
    frame = encode_weights(Stamp(RUN), tree_arrays(params), weights_hash(params))
    got = checked_tree(decode_weights(frame, RUN).message, schema, params)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(got), strict=True):
        np.testing.assert_array_equal(np.asarray(a), b)
    wider = make_agent(dataclasses.replace(NETWORK, width=32), EnvSpec()).init(jax.random.key(0))
    frame = encode_weights(Stamp(RUN), tree_arrays(wider), weights_hash(wider))
    with pytest.raises(Rejected) as refused:
        check(decode_weights(frame, RUN).message, schema)
    assert refused.value.reason == "tree_hash"
