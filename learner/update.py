"""The PPO update: one pure function of (train state, trajectory batch), used unchanged by the fused trainer and
the distributed learner.

A batch (`actors.trajectory.TrajectoryBatch`) is E environment sequences of T steps collected by a behaviour
policy that may be some versions older than the one being trained; the update measures that lag against the
batch's behaviour version (whether to train on a stale batch at all is the caller's decision, see
`check_policy_lag`), and learns only from the steps the batch's train mask keeps. Targets and advantages come
from GAE (on-policy, `correction = "none"`) or V-trace (importance-weighted, robust to policy lag) computed once
per update with the current parameters; then
`update_epochs` passes over `num_minibatches` minibatches of whole sequences apply the clipped PPO loss, centred
on the learner's log-probabilities before the update (or, with `proximal = "behaviour"`, on the behaviour's;
`learner.losses`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from impulse.actors.trajectory import Trajectory, TrajectoryBatch
from impulse.engine.pytree import all_finite
from impulse.learner.config import PPOConfig
from impulse.learner.losses import PPOBatch, approx_kl, ppo_loss, weighted_mean
from impulse.learner.returns import gae, vtrace

Array = jax.Array


class TrainState(NamedTuple):
    """Everything the update changes. `policy_version` counts updates: actors tag data with it."""

    params: Any
    opt_state: Any
    policy_version: Array  # int32


class LagCheck(NamedTuple):
    lag: Any  # policy versions between the data's behaviour policy and the learner's
    accepted: Any  # bool: lag within the configured limit and not negative


def check_policy_lag(behaviour_version: Any, learner_version: Any, max_policy_lag: int) -> LagCheck:
    """How stale a batch is: the one staleness rule, on the host (Python ints, as the learner's intake judges a
    frame) and on the device (int32 arrays, as the update reports it). Batches older than `max_policy_lag` versions
    are dropped (and counted by the caller) rather than corrected: importance weights that far off-policy are mostly
    clipped and carry little signal. A batch acted by a policy newer than the learner's (a lag below 0) is never
    accepted: no weights of this learner made it."""
    lag = learner_version - behaviour_version
    return LagCheck(lag=lag, accepted=(lag >= 0) & (lag <= max_policy_lag))


def make_optimizer(config: PPOConfig, num_updates: int) -> optax.GradientTransformation:
    """Adam with global-norm clipping; the learning rate decays linearly to 0 over the run when annealed."""
    steps_per_update = config.update_epochs * config.num_minibatches
    if config.anneal_lr:
        rate = optax.linear_schedule(config.learning_rate, 0.0, max(num_updates, 1) * steps_per_update)
    else:
        rate = config.learning_rate
    return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(rate, eps=1e-5))


def targets_and_advantages(
    config: PPOConfig, trajectory: Trajectory, values: Array, last_value: Array, log_ratio: Array
) -> tuple[Array, Array]:
    """(value targets, advantages) [T, E] under the configured correction. `values` and `last_value` come from
    the current parameters; `log_ratio` is log pi_current - log pi_behaviour of the taken actions."""
    discounts = config.gamma * (1.0 - trajectory.done.astype(jnp.float32))
    if config.correction == "vtrace":
        return vtrace(
            rewards=trajectory.reward,
            values=values,
            bootstrap_value=last_value,
            discounts=discounts,
            log_rhos=log_ratio,
            lambda_=config.gae_lambda,
            rho_bar=config.vtrace_rho_bar,
            c_bar=config.vtrace_c_bar,
            # The clipped PPO ratio already weights the policy gradient by pi/mu; weighting the advantages too
            # would apply the correction twice.
            pg_rho_bar=None,
        )
    return gae(
        rewards=trajectory.reward,
        values=values,
        bootstrap_value=last_value,
        discounts=discounts,
        lambda_=config.gae_lambda,
    )


def lag_metrics(log_ratio: Array, weight: Array, config: PPOConfig) -> dict[str, Array]:
    """How far the batch is off-policy, from log_ratio = log pi_learner - log pi_behaviour of the taken actions
    (the learner before the update): `behaviour_kl`, the estimated KL(behaviour || learner), and `trace_weight`,
    the mean of min(c-bar, pi_learner / pi_behaviour), the factor by which V-trace cuts each step's trace
    (1: no cut; gae_lambda multiplies it further). On-policy both are 0 and 1 up to rounding."""
    return {"behaviour_kl": approx_kl(log_ratio, weight),
            "trace_weight": weighted_mean(jnp.minimum(config.vtrace_c_bar, jnp.exp(log_ratio)), weight)}


def keep_if_finite(new: Any, old: Any, fine: Array) -> tuple[Any, Any, Array]:
    """(new or old parameters, new or old optimiser state, 1.0 if the update was skipped else 0.0): `new` = (params,
    opt_state) unless `fine` is false or a NaN or an infinity is in them, in which case the update is undone as a
    whole. One bad batch or learning rate then costs one update, not the run: a non-finite parameter would spread
    to every later update, checkpoint and actor."""
    keep = fine & all_finite(new)
    params, opt_state = jax.tree.map(lambda fresh, kept: jnp.where(keep, fresh, kept), new, old)
    return params, opt_state, 1.0 - keep.astype(jnp.float32)


def acts_finitely(apply_fn, distribution, params: Any, obs: Any, action: Array) -> Array:
    """Whether `params` give a value and a log-probability of `action` that are numbers on `obs`: parameters can
    be finite and still useless (a learning rate of 1e38 moves them to about 1e38, whose outputs overflow), and an
    actor acting with them would send only batches the learner must refuse."""
    dist_params, value = apply_fn(params, obs)
    return jnp.isfinite(value).all() & ~jnp.isnan(distribution.log_prob(dist_params, action)).any()


def ppo_update(
    state: TrainState,
    batch: TrajectoryBatch,
    key: Array,
    *,
    apply_fn,
    distribution,
    optimizer: optax.GradientTransformation,
    config: PPOConfig,
    minibatch_sharding: jax.sharding.Sharding | None = None,
) -> tuple[TrainState, dict[str, Array]]:
    """One PPO update on a [T, E] batch. Returns the new state and mean metrics over all minibatch steps (the
    loss terms and `grad_norm`, the gradients' global norm before clipping), plus `policy_lag`, the versions
    between the batch's behaviour policy and `state`, how far the batch is off-policy (`lag_metrics`), and
    `non_finite`: 1.0 when the update was skipped because something in it or in the policy it made was not finite
    (`keep_if_finite`, `acts_finitely`; the policy version still advances, to the same parameters, so both modes
    count updates alike).

    `minibatch_sharding` (see `learner.sharding`) splits every minibatch's samples over devices, so that each
    device evaluates the loss on its share and only gradients cross between them; the result is the same."""
    trajectory = batch.steps
    num_steps, num_envs = trajectory.reward.shape

    def evaluate(params, obs, action):
        dist_params, value = apply_fn(params, obs)
        return distribution.log_prob(dist_params, action), value

    flat = lambda x: x.reshape((num_steps * num_envs,) + x.shape[2:])  # noqa: E731
    log_prob, values = evaluate(state.params, jax.tree.map(flat, trajectory.obs), flat(trajectory.action))
    log_prob, values = log_prob.reshape(num_steps, num_envs), values.reshape(num_steps, num_envs)
    _, last_value = apply_fn(state.params, batch.bootstrap_obs)
    if config.correction == "vtrace":
        targets, advantages = targets_and_advantages(
            config, trajectory, values, last_value, log_prob - trajectory.log_prob
        )
    else:
        # On-policy: the behaviour values are those of the parameters that acted, as in plain PPO.
        targets, advantages = targets_and_advantages(
            config, trajectory, trajectory.value, last_value, jnp.zeros_like(log_prob)
        )
    proximal = {}
    old_value = trajectory.value
    if config.proximal == "learner":
        # Decoupled PPO: the clip is centred on the learner's policy before this update (and the value clip on its
        # values); the behaviour's lag is corrected by a truncated importance weight instead.
        proximal = {"proximal_log_prob": jax.lax.stop_gradient(log_prob),
                    "importance": jax.lax.stop_gradient(
                        jnp.minimum(config.vtrace_rho_bar, jnp.exp(log_prob - trajectory.log_prob)))}
        old_value = jax.lax.stop_gradient(values)
    samples = PPOBatch(
        obs=trajectory.obs,
        action=trajectory.action,
        behaviour_log_prob=trajectory.log_prob,
        old_value=old_value,
        advantage=jax.lax.stop_gradient(advantages),
        target=jax.lax.stop_gradient(targets),
        weight=batch.train_mask.astype(jnp.float32),
        **proximal,
    )

    def loss_fn(params, minibatch: PPOBatch):
        return ppo_loss(params, apply_fn, distribution, minibatch, config)

    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def minibatch_step(carry, minibatch):
        params, opt_state = carry
        (_, metrics), grads = grad_fn(params, minibatch)
        metrics["grad_norm"] = optax.tree.norm(grads)  # before clipping
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), metrics

    def epoch(carry, epoch_key):
        # Minibatches are whole environment sequences: shuffle the environment axis, split it.
        order = jax.random.permutation(epoch_key, num_envs)
        per = num_envs // config.num_minibatches

        def split(x):
            # [T, E] -> [minibatch, env, T] -> [minibatch, env * T]: env-major, so a split of the samples over
            # devices is a split of environments.
            x = jnp.take(x, order, axis=1).reshape((num_steps, config.num_minibatches, per) + x.shape[2:])
            x = jnp.moveaxis(x, 0, 2).reshape((config.num_minibatches, per * num_steps) + x.shape[3:])
            if minibatch_sharding is not None:
                x = jax.lax.with_sharding_constraint(x, minibatch_sharding)
            return x

        return jax.lax.scan(minibatch_step, carry, jax.tree.map(split, samples))

    (params, opt_state), metrics = jax.lax.scan(
        epoch, (state.params, state.opt_state), jax.random.split(key, config.update_epochs)
    )
    metrics = jax.tree.map(jnp.mean, metrics)
    # Skipped if anything is not finite: the loss metrics (grad_norm among them, so the gradients count), the new
    # parameters and optimiser state, or the new policy's outputs on the batch's last observations.
    fine = all_finite(metrics) & acts_finitely(apply_fn, distribution, params, batch.bootstrap_obs,
                                               trajectory.action[-1])
    params, opt_state, metrics["non_finite"] = keep_if_finite((params, opt_state), (state.params, state.opt_state),
                                                              fine)
    metrics["policy_lag"] = check_policy_lag(jnp.asarray(batch.behaviour_version, jnp.int32),
                                             jnp.asarray(state.policy_version, jnp.int32), 0).lag
    metrics["trained_fraction"] = batch.train_mask.mean()
    metrics.update(lag_metrics(log_prob - trajectory.log_prob, batch.train_mask.astype(jnp.float32), config))
    return TrainState(params, opt_state, state.policy_version + 1), metrics
