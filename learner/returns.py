"""Value targets and advantages over time-major trajectories: GAE (on-policy) and V-trace (off-policy).

Every array is time-major [T, B, ...] (any trailing batch dimensions); `bootstrap_value` [B, ...] is the value
of the observation after the last step. `discounts[t]` multiplies the value of the state after step t, so an
episode that ends at step t has `discounts[t] = 0` (callers pass `gamma * (1 - done)`); nothing flows across
that boundary. Both functions return `(targets, advantages)`; neither stops gradients (callers do, since
targets are constants of the loss). Recurrences run backwards in time with `lax.scan`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def _next_values(values: Array, bootstrap_value: Array) -> Array:
    """values shifted one step earlier in time: V(x_{t+1}) for every t, the bootstrap value for the last."""
    return jnp.concatenate([values[1:], bootstrap_value[None]], axis=0)


def _discounted_backward_sum(deltas: Array, decays: Array) -> Array:
    """acc_t = deltas_t + decays_t * acc_{t+1}, acc_T = 0, for all t (a reverse scan over time)."""

    def step(acc, inputs):
        delta, decay = inputs
        acc = delta + decay * acc
        return acc, acc

    _, out = jax.lax.scan(step, jnp.zeros_like(deltas[0]), (deltas, decays), reverse=True)
    return out


def gae(
    rewards: Array,
    values: Array,
    bootstrap_value: Array,
    discounts: Array,
    lambda_: float = 0.95,
) -> tuple[Array, Array]:
    """Generalised advantage estimation (Schulman et al., 2016).

    delta_t = r_t + discount_t V(x_{t+1}) - V(x_t); A_t = delta_t + discount_t lambda A_{t+1}.
    Returns (targets = A + V, i.e. the lambda-returns, advantages A), both [T, B]."""
    deltas = rewards + discounts * _next_values(values, bootstrap_value) - values
    advantages = _discounted_backward_sum(deltas, discounts * lambda_)
    return advantages + values, advantages


def vtrace(
    rewards: Array,
    values: Array,
    bootstrap_value: Array,
    discounts: Array,
    log_rhos: Array,
    lambda_: float = 1.0,
    rho_bar: float = 1.0,
    c_bar: float = 1.0,
    pg_rho_bar: float | None = 1.0,
) -> tuple[Array, Array]:
    """V-trace targets and policy-gradient advantages (Espeholt et al., 2018, IMPALA), with lambda as in its
    remark 2.

    `log_rhos` [T, B] = log pi(a_t|x_t) - log mu(a_t|x_t) (target policy over behaviour policy).
    rho_t = min(rho_bar, pi/mu), c_t = lambda min(c_bar, pi/mu), delta_t = rho_t (r_t + discount_t V(x_{t+1}) -
    V(x_t)); v_s - V(x_s) = delta_s + discount_s c_s (v_{s+1} - V(x_{s+1})), with v_T = bootstrap_value.
    Advantages: rho^pg_t (r_t + discount_t v_{t+1} - V(x_t)), with rho^pg_t = min(pg_rho_bar, pi/mu) as in the
    paper; `pg_rho_bar=None` leaves them unweighted, for losses that apply the ratio themselves (PPO's surrogate
    already multiplies by pi/mu). On-policy (log_rhos = 0) with bars >= 1, targets equal GAE's lambda-returns;
    the advantages do not equal GAE's for lambda < 1: they are delta_t + discount_t (v_{t+1} - V(x_{t+1})), where
    GAE discounts the same tail by a further lambda.
    Returns (targets v [T, B], advantages [T, B])."""
    rhos = jnp.exp(log_rhos)
    clipped_rhos = jnp.minimum(rho_bar, rhos)
    cs = lambda_ * jnp.minimum(c_bar, rhos)
    next_values = _next_values(values, bootstrap_value)
    deltas = clipped_rhos * (rewards + discounts * next_values - values)
    targets = values + _discounted_backward_sum(deltas, discounts * cs)
    next_targets = _next_values(targets, bootstrap_value)
    advantages = rewards + discounts * next_targets - values
    if pg_rho_bar is not None:
        advantages = jnp.minimum(pg_rho_bar, rhos) * advantages
    return targets, advantages
