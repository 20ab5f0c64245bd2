"""The PPO loss (Schulman et al., 2017), piece by piece.

Each piece is a small pure function of arrays, so that tests can check it by hand; `ppo_loss` evaluates the
network on a minibatch and puts them together. Ratios are taken against the centre of the clip, the proximal
policy. By default (`ppo.proximal = "learner"`) that is the learner's own policy at the start of the update, and
each sample is weighted by the truncated importance ratio min(rho-bar, pi_proximal / mu): the decoupled objective
of Hilton et al. (2022, "Batch size-invariance for policy optimization"), under which the trust region is the
learner's and a lagging actor's batch is not clipped merely for being old. With `ppo.proximal = "behaviour"` it is
the behaviour policy (the log-probabilities recorded when the data was collected), as in classic PPO. On-policy
both are the same objective.

Every mean is over the samples the batch trains on: a `weight` of 0 (a step of a level a curriculum only
evaluates) removes a sample from the loss and the statistics without changing any shape.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from impulse.learner.config import PPOConfig
from impulse.learner.distributions import Distribution

Array = jax.Array


class PPOBatch(NamedTuple):
    """One minibatch; every leaf has the same leading dimensions (any number of them, e.g. [N] or [T, B])."""

    obs: Any
    action: Array
    behaviour_log_prob: Array  # log mu(a|x), recorded by the acting policy
    old_value: Array  # the acting policy's value estimate, the centre of the value clip
    advantage: Array
    target: Array  # value target (GAE lambda-return or V-trace v_s)
    weight: Array  # 1.0 for samples to learn from, 0.0 for those to leave out
    proximal_log_prob: Array | None = None  # the clip's centre, log pi_proximal(a|x); None: the behaviour's
    importance: Array | None = None  # min(rho-bar, pi_proximal / mu) per sample; None: 1


def weighted_mean(x: Array, weight: Array | None = None) -> Array:
    """The mean of `x` over the samples with weight 1 (the plain mean without weights); 0 if none count."""
    if weight is None:
        return jnp.mean(x)
    return jnp.sum(x * weight) / jnp.maximum(jnp.sum(weight), 1.0)


def normalize_advantages(advantages: Array, eps: float = 1e-8, weight: Array | None = None) -> Array:
    """Zero mean, unit standard deviation over the counted entries."""
    mean = weighted_mean(advantages, weight)
    std = jnp.sqrt(weighted_mean(jnp.square(advantages - mean), weight))
    return (advantages - mean) / (std + eps)


def policy_loss(
    log_prob: Array, centre_log_prob: Array, advantages: Array, clip_eps: float, weight: Array | None = None,
    importance: Array | None = None,
) -> Array:
    """Clipped surrogate: -mean(w min(r A, clip(r, 1 - eps, 1 + eps) A)), r = exp(log_prob - centre_log_prob), w
    the samples' `importance` weights (1 where None)."""
    ratio = jnp.exp(log_prob - centre_log_prob)
    unclipped = ratio * advantages
    clipped = jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages
    surrogate = jnp.minimum(unclipped, clipped)
    if importance is not None:
        surrogate = importance * surrogate
    return -weighted_mean(surrogate, weight)


def value_loss(
    values: Array, old_values: Array, targets: Array, clip_eps: float | None, weight: Array | None = None
) -> Array:
    """0.5 mean squared error to the targets; with `clip_eps`, the pessimistic (larger) of the errors of the
    prediction and of the prediction clipped to old_values +- clip_eps."""
    error = jnp.square(values - targets)
    if clip_eps is not None:
        clipped = old_values + jnp.clip(values - old_values, -clip_eps, clip_eps)
        error = jnp.maximum(error, jnp.square(clipped - targets))
    return 0.5 * weighted_mean(error, weight)


def entropy_bonus(entropy: Array, weight: Array | None = None) -> Array:
    """Mean entropy of the policy over the batch (subtracted from the loss, scaled by ent_coef)."""
    return weighted_mean(entropy, weight)


def total_loss(policy: Array, value: Array, entropy: Array, vf_coef: float, ent_coef: float) -> Array:
    """policy + vf_coef * value - ent_coef * entropy."""
    return policy + vf_coef * value - ent_coef * entropy


def approx_kl(log_ratio: Array, weight: Array | None = None) -> Array:
    """Estimate of KL(mu || pi) from log_ratio = log pi - log mu of actions drawn from mu: mean((r - 1) - log r),
    unbiased and never negative (Schulman's k3 estimator)."""
    return weighted_mean(jnp.expm1(log_ratio) - log_ratio, weight)


def clip_fraction(log_ratio: Array, clip_eps: float, weight: Array | None = None) -> Array:
    """Fraction of samples whose ratio lies outside [1 - eps, 1 + eps]."""
    return weighted_mean((jnp.abs(jnp.exp(log_ratio) - 1.0) > clip_eps).astype(jnp.float32), weight)


def ppo_loss(
    params: Any, apply_fn, distribution: Distribution, batch: PPOBatch, config: PPOConfig
) -> tuple[Array, dict[str, Array]]:
    """PPO loss of one minibatch and its metrics.

    `apply_fn(params, obs) -> (distribution params, value)` (see `learner.networks.ActorCritic`); leading
    dimensions of the batch pass straight through it. Uses config.clip_eps (also for the value clip when
    config.clip_value), vf_coef, ent_coef and normalize_advantages. Returns (total loss, metrics) with metrics
    total_loss, policy_loss, value_loss, entropy, approx_kl, clip_fraction (both measured from the clip's
    centre)."""
    dist_params, values = apply_fn(params, batch.obs)
    log_prob = distribution.log_prob(dist_params, batch.action)
    weight = batch.weight
    advantages = batch.advantage
    if config.normalize_advantages:
        advantages = normalize_advantages(advantages, weight=weight)
    centre = batch.behaviour_log_prob if batch.proximal_log_prob is None else batch.proximal_log_prob
    pi_loss = policy_loss(log_prob, centre, advantages, config.clip_eps, weight, batch.importance)
    v_loss = value_loss(values, batch.old_value, batch.target, config.clip_eps if config.clip_value else None,
                        weight)
    entropy = entropy_bonus(distribution.entropy(dist_params), weight)
    loss = total_loss(pi_loss, v_loss, entropy, config.vf_coef, config.ent_coef)
    log_ratio = jax.lax.stop_gradient(log_prob - centre)
    metrics = {
        "total_loss": loss,
        "policy_loss": pi_loss,
        "value_loss": v_loss,
        "entropy": entropy,
        "approx_kl": approx_kl(log_ratio, weight),
        "clip_fraction": clip_fraction(log_ratio, config.clip_eps, weight),
    }
    return loss, metrics
