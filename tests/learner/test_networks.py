"""Networks: output shapes for S/M/L observations, parameter counts, permutation invariance, and that inactive
entities do not matter. Shapes and counts use abstract evaluation (no compilation). Numerical checks run eagerly
on random parameters of the initialiser's shapes (the properties hold for any parameters, and flax's orthogonal
initialisers are slow outside jit): a small transformer and the default-sized permutation-invariant MLP."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.env.actions import action_space
from impulse.engine.env.observations import observation_shape
from impulse.engine.env.spec import EnvSpec
from impulse.engine.physics.sizes import size_preset
from impulse.learner.config import NetworkConfig
from impulse.learner.distributions import Categorical, DiagGaussian, MultiCategorical, distribution_for
from impulse.learner.networks import count_parameters, describe_parameters, make_network, parameter_counts
from tests.support.learner_dummies import SIZES, dummy_observation, permute_shapes, scramble_inactive
from tests.support.quick_compile import quick_jit

MULTI = MultiCategorical((3, 3, 3, 3, 2, 2))
SMALL_TRANSFORMER = NetworkConfig(
    kind="transformer", width=32, depth=2, transformer_encoder_size=32, transformer_size=8, num_heads=8
)
FLAT_LENGTH = {"s": 140, "m": 247, "l": 679}
# Kinetix's own counts for the same layer sizes (its digest, section 12.2): the PI-MLP and the flat MLP (S, L).
KINETIX_ENTITY_PARAMS = 221_521
KINETIX_FLAT_PARAMS = {"s": 185_361, "l": 254_353}


def abstract_params(network, obs):
    return jax.eval_shape(network.init, jax.random.key(0), obs)


@pytest.mark.parametrize("kind", ["transformer", "entity"])
@pytest.mark.parametrize("size", ["s", "m", "l"])
@pytest.mark.parametrize("distribution", [MULTI, Categorical(11), DiagGaussian(6)], ids=["multi", "discrete", "cont"])
def test_entity_network_output_shapes(kind: str, size: str, distribution) -> None:
    network = make_network(NetworkConfig(kind=kind), distribution)
    obs = jax.eval_shape(lambda: dummy_observation(size, batch=(4,)))
    params = abstract_params(network, obs)
    dist_params, value = jax.eval_shape(network.apply, params, obs)
    assert dist_params.shape == (4, distribution.num_params) and value.shape == (4,)
    assert dist_params.dtype == value.dtype == jnp.float32


@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_any_leading_dimensions(batch: tuple[int, ...]) -> None:
    for kind in ("transformer", "entity"):
        network = make_network(NetworkConfig(kind=kind), MULTI)
        obs = jax.eval_shape(lambda b=batch: dummy_observation("m", batch=b) if b else _unbatched("m"))
        dist_params, value = jax.eval_shape(network.apply, abstract_params(network, obs), obs)
        assert dist_params.shape == batch + (16,) and value.shape == batch
    flat = make_network(NetworkConfig(kind="flat"), MULTI)
    vector = jax.ShapeDtypeStruct(batch + (FLAT_LENGTH["m"],), jnp.float32)
    dist_params, value = jax.eval_shape(flat.apply, abstract_params(flat, vector), vector)
    assert dist_params.shape == batch + (16,) and value.shape == batch


def _unbatched(size: str):
    return jax.tree.map(lambda x: x[0], dummy_observation(size, batch=(1,)))


def test_dummy_observations_match_the_environment_layout() -> None:
    for size in "sml":
        real = observation_shape(EnvSpec(sizes=size_preset(size)))
        dummy = jax.eval_shape(lambda s=size: _unbatched(s))
        for name in real.__dataclass_fields__:
            assert getattr(dummy, name).shape == getattr(real, name).shape, (size, name)


def test_parameter_counts_at_default_sizes(capsys) -> None:
    lines = []
    for kind in ("transformer", "entity", "flat"):
        for size in "sml":
            network = make_network(NetworkConfig(kind=kind), MULTI)
            if kind == "flat":
                obs = jax.ShapeDtypeStruct((FLAT_LENGTH[size],), jnp.float32)
            else:
                obs = jax.eval_shape(lambda s=size: _unbatched(s))
            params = abstract_params(network, obs)
            total = count_parameters(params)
            assert total > 0 and parameter_counts(params)["total"] == total
            lines.append(f"{kind:<12} {size}  {total:>9,}")
            if kind == "entity":
                assert total == KINETIX_ENTITY_PARAMS
            if kind == "flat" and size in KINETIX_FLAT_PARAMS:
                assert total == KINETIX_FLAT_PARAMS[size]
        if kind == "transformer":
            print(describe_parameters(params))
    with capsys.disabled():
        print("\nparameters (multi-discrete heads):\n" + "\n".join(lines))
    # The gaussian head adds one log-std per action dimension and has 6 outputs where multi-discrete has 16.
    obs = jax.eval_shape(lambda: _unbatched("s"))
    multi = count_parameters(abstract_params(make_network(NetworkConfig(kind="entity"), MULTI), obs))
    gauss = count_parameters(abstract_params(make_network(NetworkConfig(kind="entity"), DiagGaussian(6)), obs))
    assert gauss == multi - 10 * 129 + 6


@functools.cache
def jitted_apply(config: NetworkConfig, distribution):
    """One compiled apply per network, shared by the tests (which reuse a few observation shapes)."""
    return quick_jit(make_network(config, distribution).apply)


def _init(network, obs, seed: int = 0):
    """Random parameters with the initialiser's shapes: kernels N(0, 1 / fan-in), biases N(0, 0.1^2)."""
    rng = np.random.default_rng(seed)

    def fill(leaf):
        scale = 1.0 / np.sqrt(np.prod(leaf.shape[:-1])) if leaf.ndim > 1 else 0.1
        return jnp.asarray(rng.normal(size=leaf.shape) * scale, leaf.dtype)

    return jax.tree.map(fill, abstract_params(network, obs))


@pytest.mark.parametrize("size", ["s", "l"])
def test_pi_mlp_is_permutation_invariant(size: str) -> None:
    network = make_network(NetworkConfig(kind="entity"), MULTI)
    obs = dummy_observation(size, batch=(3,))
    params = _init(network, obs)
    apply = jitted_apply(network.config, MULTI)
    dist_params, value = apply(params, obs)
    rng = np.random.default_rng(1)
    P, C, _, _ = SIZES[size]
    for _ in range(2):
        permuted = permute_shapes(obs, rng.permutation(P), rng.permutation(C))
        p2, v2 = apply(params, permuted)
        np.testing.assert_allclose(p2, dist_params, atol=1e-5)
        np.testing.assert_allclose(v2, value, atol=1e-5)
    # joint and thruster rows too (the PI network reads no indices)
    J2 = obs.joints.shape[-2]
    order = rng.permutation(J2)
    moved = obs.replace(joints=obs.joints[:, order], joint_mask=obs.joint_mask[:, order])
    np.testing.assert_allclose(apply(params, moved)[1], value, atol=1e-5)


def test_transformer_is_permutation_invariant() -> None:
    size = "l"
    network = make_network(SMALL_TRANSFORMER, MULTI)
    obs = dummy_observation(size, batch=(3,))
    params = _init(network, obs)
    apply = jitted_apply(network.config, MULTI)
    dist_params, value = apply(params, obs)
    rng = np.random.default_rng(2)
    P, C, _, _ = SIZES[size]
    p2, v2 = apply(params, permute_shapes(obs, rng.permutation(P), rng.permutation(C)))
    np.testing.assert_allclose(p2, dist_params, atol=1e-5)
    np.testing.assert_allclose(v2, value, atol=1e-5)


@pytest.mark.parametrize("config", [SMALL_TRANSFORMER, NetworkConfig(kind="entity")], ids=["transformer", "entity"])
def test_inactive_entities_do_not_matter(config: NetworkConfig) -> None:
    network = make_network(config, MULTI)
    obs = dummy_observation("l", batch=(3,))
    params = _init(network, obs)
    apply = jitted_apply(network.config, MULTI)
    dist_params, value = apply(params, obs)
    p2, v2 = apply(params, scramble_inactive(obs))
    np.testing.assert_allclose(p2, dist_params, atol=1e-6)
    np.testing.assert_allclose(v2, value, atol=1e-6)
    # ...while an active entity's features do matter
    p3, v3 = apply(params, obs.replace(circles=obs.circles + obs.circle_mask[..., None]))
    assert not np.allclose(v3, value, atol=1e-4)


def test_transformer_reads_joint_structure_and_attention_channels() -> None:
    network = make_network(SMALL_TRANSFORMER, MULTI)
    obs = dummy_observation("l", batch=(3,), seed=5)
    params = _init(network, obs)
    apply = jitted_apply(network.config, MULTI)
    _, value = apply(params, obs)
    joints = obs.joints + obs.joint_mask[..., None]  # active joint rows change: messages change
    assert not np.allclose(apply(params, obs.replace(joints=joints))[1], value, atol=1e-4)
    contact = obs.attention_mask.at[:, 3].set(obs.attention_mask[:, 0])  # "touching" channel: all active pairs
    assert not np.allclose(apply(params, obs.replace(attention_mask=contact))[1], value, atol=1e-4)


def test_leading_dimensions_give_the_same_numbers() -> None:
    network = make_network(NetworkConfig(kind="entity"), MULTI)
    obs = dummy_observation("l", batch=(3,))
    params = _init(network, obs)
    apply = jitted_apply(network.config, MULTI)
    p, v = apply(params, obs)
    host = jax.tree.map(np.asarray, obs)  # reshaped and indexed by numpy, which compiles nothing
    p_2d, v_2d = apply(params, jax.tree.map(lambda x: x.reshape((3, 1) + x.shape[1:]), host))
    np.testing.assert_allclose(p_2d[:, 0], p, atol=1e-5)
    np.testing.assert_allclose(v_2d[:, 0], v, atol=1e-5)
    one, _ = apply(params, jax.tree.map(lambda x: x[1], host))
    np.testing.assert_allclose(one, p[1], atol=1e-5)


def test_gaussian_head_has_state_independent_log_std() -> None:
    config = NetworkConfig(kind="flat", width=8, depth=1, flat_embedding_size=8)
    network = make_network(config, distribution_for(action_space(EnvSpec(action="continuous"))))
    obs = jnp.asarray(np.random.default_rng(0).normal(size=(4, FLAT_LENGTH["s"])), jnp.float32)

    def init_and_apply(key, obs):
        params = network.init(key, obs)
        return params, network.apply(params, obs)

    params, (dist_params, value) = quick_jit(init_and_apply)(jax.random.key(0), obs)
    assert params["params"]["heads"]["log_std"].shape == (6,)
    assert dist_params.shape == (4, 12) and value.shape == (4,)
    np.testing.assert_array_equal(dist_params[:, 6:], 0.0)  # log-std starts at 0, the same for every state
    assert float(np.abs(np.asarray(dist_params)[:, :6]).max()) < 0.5  # means start small (actor output scale 0.01)


def test_wrong_observation_for_kind_is_an_error() -> None:
    obs = _unbatched("s")
    with pytest.raises(TypeError, match="flat"):
        make_network(NetworkConfig(kind="flat"), MULTI).init(jax.random.key(0), obs)
    with pytest.raises(TypeError, match="EntityObservation"):
        make_network(NetworkConfig(kind="entity"), MULTI).init(jax.random.key(0), jnp.zeros(140))


def test_heads_per_channel_must_divide() -> None:
    with pytest.raises(ValueError, match="multiple of 4"):
        NetworkConfig(num_heads=6)
    NetworkConfig(num_heads=6, full_attention_mask=True)


def test_ppo_loss_gradients_flow_through_the_network() -> None:
    from impulse.learner.config import PPOConfig
    from impulse.learner.losses import PPOBatch, ppo_loss

    network = make_network(dataclasses.replace(SMALL_TRANSFORMER, transformer_layers=1, depth=1), MULTI)
    obs = dummy_observation("s", batch=(2, 3))  # [T, B] as a rollout would give it
    params = _init(network, obs)
    batch = PPOBatch(
        obs=obs,
        action=jnp.asarray(np.random.default_rng(0).integers(0, 2, (2, 3, 6)), jnp.int32),
        behaviour_log_prob=jnp.full((2, 3), -5.0),
        old_value=jnp.zeros((2, 3)),
        advantage=jnp.arange(6.0).reshape(2, 3),
        target=jnp.ones((2, 3)),
        weight=jnp.ones((2, 3)),
    )
    grad_fn = quick_jit(jax.value_and_grad(ppo_loss, has_aux=True), static_argnums=(1, 2, 4))
    (loss, metrics), grads = grad_fn(params, network.apply, MULTI, batch, PPOConfig())
    assert np.isfinite(float(loss)) and set(metrics) >= {"approx_kl", "clip_fraction", "entropy"}
    leaves = jax.tree_util.tree_leaves_with_path(jax.device_get(grads))
    assert all(np.all(np.isfinite(g)) for _, g in leaves)
    # every parameter gets a gradient (the summary token, gates and message layers included)
    unused = [jax.tree_util.keystr(path) for path, g in leaves if not np.any(g != 0)]
    assert not unused, unused
