"""Action distributions against closed forms worked out in numpy, and sampling frequencies."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.env.actions import action_space
from impulse.engine.env.spec import EnvSpec
from impulse.learner.distributions import Categorical, DiagGaussian, MultiCategorical, distribution_for

KINETIX_NVEC = (3, 3, 3, 3, 2, 2)


def np_log_softmax(logits: np.ndarray) -> np.ndarray:
    shifted = logits - logits.max(axis=-1, keepdims=True)
    return shifted - np.log(np.exp(shifted).sum(axis=-1, keepdims=True))


def test_categorical_log_prob_entropy_mode_match_numpy() -> None:
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(5, 11)).astype(np.float32) * 2.0
    actions = rng.integers(0, 11, 5)
    dist = Categorical(11)
    log_p = np_log_softmax(logits.astype(np.float64))
    np.testing.assert_allclose(
        dist.log_prob(jnp.asarray(logits), jnp.asarray(actions)), log_p[np.arange(5), actions], rtol=1e-5
    )
    np.testing.assert_allclose(dist.entropy(jnp.asarray(logits)), -(np.exp(log_p) * log_p).sum(-1), rtol=1e-5)
    np.testing.assert_array_equal(dist.mode(jnp.asarray(logits)), logits.argmax(-1))
    assert dist.num_params == 11


def test_categorical_uniform_entropy_is_log_n() -> None:
    assert float(Categorical(11).entropy(jnp.zeros(11))) == pytest.approx(math.log(11), rel=1e-6)


def test_categorical_sampling_frequencies() -> None:
    probs = np.array([0.5, 0.3, 0.15, 0.05])
    logits = jnp.broadcast_to(jnp.log(jnp.asarray(probs, jnp.float32)), (20000, 4))
    samples = np.asarray(Categorical(4).sample(logits, jax.random.key(0)))
    assert samples.dtype == np.int32 and samples.shape == (20000,)
    np.testing.assert_allclose(np.bincount(samples, minlength=4) / 20000, probs, atol=0.015)


def test_multi_categorical_matches_sum_of_independent_categoricals() -> None:
    rng = np.random.default_rng(1)
    logits = rng.normal(size=(2, 3, 16)).astype(np.float32)
    actions = np.stack([rng.integers(0, n, (2, 3)) for n in KINETIX_NVEC], axis=-1)
    dist = MultiCategorical(KINETIX_NVEC)
    log_prob, entropy, mode = 0.0, 0.0, []
    start = 0
    for i, n in enumerate(KINETIX_NVEC):
        log_p = np_log_softmax(logits[..., start : start + n].astype(np.float64))
        log_prob = log_prob + np.take_along_axis(log_p, actions[..., i : i + 1], axis=-1)[..., 0]
        entropy = entropy - (np.exp(log_p) * log_p).sum(-1)
        mode.append(log_p.argmax(-1))
        start += n
    assert dist.num_params == 16
    np.testing.assert_allclose(dist.log_prob(jnp.asarray(logits), jnp.asarray(actions)), log_prob, rtol=1e-5)
    np.testing.assert_allclose(dist.entropy(jnp.asarray(logits)), entropy, rtol=1e-5)
    np.testing.assert_array_equal(dist.mode(jnp.asarray(logits)), np.stack(mode, axis=-1))


def test_multi_categorical_uniform_entropy_and_gradients_finite() -> None:
    dist = MultiCategorical(KINETIX_NVEC)
    expected = 4 * math.log(3) + 2 * math.log(2)
    assert float(dist.entropy(jnp.zeros(16))) == pytest.approx(expected, rel=1e-6)
    action = jnp.array([0, 1, 2, 0, 1, 0])
    grad = jax.grad(lambda p: dist.entropy(p) + dist.log_prob(p, action))(jnp.ones(16))
    assert np.all(np.isfinite(grad))


def test_multi_categorical_sampling_frequencies_per_dimension() -> None:
    dist = MultiCategorical(KINETIX_NVEC)
    probs = [np.array([0.6, 0.3, 0.1])] * 4 + [np.array([0.8, 0.2])] * 2
    logits = jnp.asarray(np.concatenate([np.log(p) for p in probs]), jnp.float32)
    samples = np.asarray(dist.sample(jnp.broadcast_to(logits, (20000, 16)), jax.random.key(1)))
    assert samples.shape == (20000, 6) and samples.dtype == np.int32
    for i, (n, p) in enumerate(zip(KINETIX_NVEC, probs)):
        assert samples[:, i].max() < n  # padding values are never drawn
        np.testing.assert_allclose(np.bincount(samples[:, i], minlength=n) / 20000, p, atol=0.015)


def test_diag_gaussian_matches_closed_form() -> None:
    rng = np.random.default_rng(2)
    mean = rng.normal(size=(4, 6))
    log_std = rng.normal(size=(4, 6)) * 0.5
    action = rng.normal(size=(4, 6))
    params = jnp.asarray(np.concatenate([mean, log_std], axis=-1), jnp.float32)
    var = np.exp(2 * log_std)
    expected_log_prob = (-0.5 * np.log(2 * np.pi * var) - (action - mean) ** 2 / (2 * var)).sum(-1)
    expected_entropy = (0.5 * np.log(2 * np.pi * np.e * var)).sum(-1)
    dist = DiagGaussian(6)
    assert dist.num_params == 12
    np.testing.assert_allclose(dist.log_prob(params, jnp.asarray(action, jnp.float32)), expected_log_prob, rtol=1e-5)
    np.testing.assert_allclose(dist.entropy(params), expected_entropy, rtol=1e-5)
    np.testing.assert_allclose(dist.mode(params), mean, rtol=1e-6)


def test_diag_gaussian_sample_moments() -> None:
    mean, std = np.array([0.5, -1.0]), np.array([0.2, 2.0])
    params = jnp.broadcast_to(jnp.asarray(np.concatenate([mean, np.log(std)]), jnp.float32), (20000, 4))
    samples = np.asarray(DiagGaussian(2).sample(params, jax.random.key(3)))
    np.testing.assert_allclose(samples.mean(0), mean, atol=0.05)
    np.testing.assert_allclose(samples.std(0), std, rtol=0.03)


@pytest.mark.parametrize(
    "kind, expected",
    [
        ("multi_discrete", MultiCategorical(KINETIX_NVEC)),
        ("discrete", Categorical(11)),
        ("continuous", DiagGaussian(6)),
    ],
)
def test_distribution_for_action_space(kind: str, expected) -> None:
    assert distribution_for(action_space(EnvSpec(action=kind))) == expected
