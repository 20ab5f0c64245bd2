"""PPO loss pieces against numbers worked out by hand (in the comments)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.learner.config import PPOConfig
from impulse.learner.distributions import Categorical
from impulse.learner.losses import (
    PPOBatch,
    approx_kl,
    clip_fraction,
    entropy_bonus,
    normalize_advantages,
    policy_loss,
    ppo_loss,
    total_loss,
    value_loss,
)

RATIOS = np.array([1.5, 0.5, 1.1, 0.7])
ADVANTAGES = jnp.array([1.0, 1.0, -2.0, -1.0])
# With eps 0.2: min(r A, clip(r) A) = min(1.5, 1.2) = 1.2; min(0.5, 0.8) = 0.5; min(-2.2, -2.2) = -2.2;
# min(-0.7, -0.8) = -0.8. Sum -1.3, mean -0.325, loss +0.325.
POLICY_LOSS = 0.325
VALUES = jnp.array([1.0, 2.0, 0.0, 0.0])
OLD_VALUES = jnp.array([0.5, 2.5, 0.0, 0.0])
TARGETS = jnp.array([2.0, 1.0, 0.1, 0.0])
# Unclipped squared errors 1, 1, 0.01, 0. Clipped predictions 0.5 + 0.2 = 0.7 and 2.5 - 0.2 = 2.3: errors
# 1.69, 1.69, 0.01, 0; the larger of each pair is 1.69, 1.69, 0.01, 0: mean 0.8475, half 0.42375.
VALUE_LOSS_CLIPPED = 0.42375
VALUE_LOSS_UNCLIPPED = 0.5 * 2.01 / 4


def test_policy_loss_by_hand() -> None:
    log_prob = jnp.log(jnp.asarray(RATIOS)) + 0.3  # the ratio is what matters, not the level
    behaviour = jnp.full(4, 0.3)
    assert float(policy_loss(log_prob, behaviour, ADVANTAGES, 0.2)) == pytest.approx(POLICY_LOSS, abs=1e-6)


def test_policy_loss_gradient_vanishes_where_clipped() -> None:
    # Samples 0 (r = 1.5 > 1.2, A > 0) and 3 (r = 0.7 < 0.8, A < 0) are clipped: no gradient. Others: -r A / 4.
    grad = jax.grad(policy_loss)(jnp.log(jnp.asarray(RATIOS)), jnp.zeros(4), ADVANTAGES, 0.2)
    np.testing.assert_allclose(grad, [0.0, -0.5 / 4, 2.2 / 4, 0.0], rtol=1e-6, atol=1e-7)


def test_importance_weights_scale_each_sample_of_the_surrogate() -> None:
    # Surrogates 1.2, 0.5, -2.2, -0.8 (above) weighted by 0.5, 1, 1, 0: 0.6 + 0.5 - 2.2 = -1.1, mean -0.275.
    importance = jnp.array([0.5, 1.0, 1.0, 0.0])
    loss = policy_loss(jnp.log(jnp.asarray(RATIOS)), jnp.zeros(4), ADVANTAGES, 0.2, importance=importance)
    assert float(loss) == pytest.approx(0.275, abs=1e-6)


def test_the_clip_centred_on_the_learner_keeps_the_gradient_of_a_lagging_batch() -> None:
    """A sample the learner's policy already favours 1.5 times more than the lagging behaviour policy did, with a
    positive advantage: centred on the behaviour, the ratio 1.5 is clipped and the sample teaches nothing;
    centred on the learner (ratio 1, weight min(1, 1.5) = 1), it pushes the action up."""
    config = PPOConfig(normalize_advantages=False, clip_eps=0.2, vf_coef=0.0, ent_coef=0.0)
    params = {"logit": jnp.zeros(()), "value": jnp.zeros(1)}
    learner = jnp.full(1, math.log(0.5))  # the fixed policy's log pi(a = 0)
    behaviour = learner - math.log(1.5)
    lagging = PPOBatch(obs=jnp.zeros(1), action=jnp.zeros(1, jnp.int32), behaviour_log_prob=behaviour,
                       old_value=jnp.zeros(1), advantage=jnp.ones(1), target=jnp.zeros(1), weight=jnp.ones(1))
    centred = lagging._replace(proximal_log_prob=learner, importance=jnp.minimum(1.0, jnp.exp(learner - behaviour)))

    def policy(params, obs):  # pi(a = 0) = sigmoid(logit): one half at logit 0
        return jnp.stack([params["logit"] + 0.0 * obs, 0.0 * obs], axis=-1), params["value"] + 0.0 * obs

    def grad_and_clip(batch: PPOBatch) -> tuple[float, float]:
        grads, metrics = jax.grad(ppo_loss, has_aux=True)(params, policy, Categorical(2), batch, config)
        return float(grads["logit"]), float(metrics["clip_fraction"])

    assert grad_and_clip(lagging) == (0.0, 1.0)
    gradient, clipped = grad_and_clip(centred)
    assert clipped == 0.0
    assert gradient == pytest.approx(-0.5, abs=1e-6)  # d/dlogit of -pi(a=0) / 0.5 = -sigmoid'(0) / 0.5


def test_value_loss_by_hand() -> None:
    assert float(value_loss(VALUES, OLD_VALUES, TARGETS, 0.2)) == pytest.approx(VALUE_LOSS_CLIPPED, abs=1e-6)
    assert float(value_loss(VALUES, OLD_VALUES, TARGETS, None)) == pytest.approx(VALUE_LOSS_UNCLIPPED, abs=1e-6)


def test_entropy_total_and_normalisation_by_hand() -> None:
    assert float(entropy_bonus(jnp.array([1.0, 2.0, 3.0]))) == pytest.approx(2.0)
    # 0.3 + 0.5 * 0.4 - 0.01 * 2 = 0.48
    assert float(total_loss(jnp.array(0.3), jnp.array(0.4), jnp.array(2.0), 0.5, 0.01)) == pytest.approx(0.48)
    # [1, 2, 3, 4]: mean 2.5, population std sqrt(1.25)
    s = math.sqrt(1.25)
    np.testing.assert_allclose(
        normalize_advantages(jnp.array([1.0, 2.0, 3.0, 4.0])), [-1.5 / s, -0.5 / s, 0.5 / s, 1.5 / s], rtol=1e-5
    )


def test_approx_kl_and_clip_fraction_by_hand() -> None:
    # r = 2: (2 - 1) - log 2 = 0.30685; r = 1: 0. Mean 0.153426.
    assert float(approx_kl(jnp.log(jnp.array([2.0, 1.0])))) == pytest.approx((1 - math.log(2)) / 2, rel=1e-5)
    # |r - 1| = 0.5, 0.5, 0.1, 0.3 against 0.2: three of four outside.
    assert float(clip_fraction(jnp.log(jnp.asarray(RATIOS)), 0.2)) == pytest.approx(0.75)


def fixed_policy(params, obs):
    """Two equally likely actions (log-prob log 0.5, entropy log 2) and a value read from params."""
    return jnp.zeros(obs.shape + (2,)) + params["logit"], params["value"] + 0.0 * obs


def test_ppo_loss_by_hand() -> None:
    config = PPOConfig(normalize_advantages=False, clip_eps=0.2, vf_coef=0.5, ent_coef=0.01)
    batch = PPOBatch(
        obs=jnp.zeros(4),
        action=jnp.array([0, 1, 0, 1]),
        behaviour_log_prob=jnp.log(0.5 / jnp.asarray(RATIOS)),  # so pi / mu = RATIOS
        old_value=OLD_VALUES,
        advantage=ADVANTAGES,
        target=TARGETS,
        weight=jnp.ones(4),
    )
    params = {"logit": jnp.zeros(()), "value": VALUES}
    loss, metrics = ppo_loss(params, fixed_policy, Categorical(2), batch, config)
    expected = POLICY_LOSS + 0.5 * VALUE_LOSS_CLIPPED - 0.01 * math.log(2)
    assert float(loss) == pytest.approx(expected, abs=1e-6)
    assert float(metrics["total_loss"]) == pytest.approx(expected, abs=1e-6)
    assert float(metrics["policy_loss"]) == pytest.approx(POLICY_LOSS, abs=1e-6)
    assert float(metrics["value_loss"]) == pytest.approx(VALUE_LOSS_CLIPPED, abs=1e-6)
    assert float(metrics["entropy"]) == pytest.approx(math.log(2), abs=1e-6)
    expected_kl = np.mean([r - 1 - math.log(r) for r in RATIOS])
    assert float(metrics["approx_kl"]) == pytest.approx(expected_kl, rel=1e-5)
    assert float(metrics["clip_fraction"]) == pytest.approx(0.75)

    unclipped_value = PPOConfig(normalize_advantages=False, clip_value=False)
    loss, _ = ppo_loss(params, fixed_policy, Categorical(2), batch, unclipped_value)
    assert float(loss) == pytest.approx(POLICY_LOSS + 0.5 * VALUE_LOSS_UNCLIPPED - 0.01 * math.log(2), abs=1e-6)


def test_ppo_loss_normalises_advantages_and_differentiates() -> None:
    batch = PPOBatch(
        obs=jnp.zeros((2, 2)),  # [T, B] leading dimensions pass through
        action=jnp.array([[0, 1], [1, 0]]),
        behaviour_log_prob=jnp.full((2, 2), math.log(0.5)),
        old_value=jnp.zeros((2, 2)),
        advantage=jnp.array([[1.0, 2.0], [3.0, 4.0]]),
        target=jnp.ones((2, 2)),
        weight=jnp.ones((2, 2)),
    )
    params = {"logit": jnp.zeros(()), "value": jnp.zeros((2, 2))}
    (loss, metrics), grads = jax.value_and_grad(ppo_loss, has_aux=True)(
        params, fixed_policy, Categorical(2), batch, PPOConfig()
    )
    # On-policy (ratio 1): normalised advantages have mean 0, so the policy loss is 0. Values equal the old
    # values, so the clip changes nothing: 0.5 * (0 - 1)^2 = 0.5.
    assert float(metrics["policy_loss"]) == pytest.approx(0.0, abs=1e-6)
    assert float(metrics["value_loss"]) == pytest.approx(0.5, abs=1e-6)
    assert float(metrics["approx_kl"]) == 0.0 and float(metrics["clip_fraction"]) == 0.0
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))


def test_weight_zero_leaves_samples_out_of_loss_and_statistics() -> None:
    """A batch with masked-out samples gives the loss and metrics of the kept samples alone."""
    config = PPOConfig(clip_eps=0.2)  # advantages normalised over the kept samples only
    full = PPOBatch(
        obs=jnp.zeros(4),
        action=jnp.array([0, 1, 0, 1]),
        behaviour_log_prob=jnp.log(0.5 / jnp.asarray(RATIOS)),
        old_value=OLD_VALUES,
        advantage=ADVANTAGES,
        target=TARGETS,
        weight=jnp.array([1.0, 0.0, 1.0, 0.0]),
    )
    kept = jax.tree.map(lambda x: x[jnp.array([0, 2])], full._replace(weight=jnp.ones(4)))
    params = {"logit": jnp.zeros(()), "value": VALUES}
    kept_params = {"logit": jnp.zeros(()), "value": VALUES[jnp.array([0, 2])]}
    loss, metrics = ppo_loss(params, fixed_policy, Categorical(2), full, config)
    kept_loss, kept_metrics = ppo_loss(kept_params, fixed_policy, Categorical(2), kept, config)
    assert float(loss) == pytest.approx(float(kept_loss), abs=1e-6)
    for name in kept_metrics:
        assert float(metrics[name]) == pytest.approx(float(kept_metrics[name]), abs=1e-6), name
    nothing, _ = ppo_loss(params, fixed_policy, Categorical(2), full._replace(weight=jnp.zeros(4)), config)
    assert float(nothing) == 0.0
