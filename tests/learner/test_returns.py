"""GAE and V-trace against plain numpy loops written from the papers' definitions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.learner.returns import gae, vtrace

T, B = 7, 3


def random_batch(seed: int = 0, done_prob: float = 0.25):
    rng = np.random.default_rng(seed)
    rewards = rng.normal(size=(T, B))
    values = rng.normal(size=(T, B))
    bootstrap = rng.normal(size=B)
    dones = rng.random((T, B)) < done_prob
    dones[2, 0] = True
    discounts = 0.9 * (1.0 - dones)
    log_rhos = rng.normal(size=(T, B)) * 0.7
    return rewards, values, bootstrap, discounts, log_rhos


def as_jax(*arrays):
    return [jnp.asarray(a, jnp.float32) for a in arrays]


def gae_reference(rewards, values, bootstrap, discounts, lam):
    advantages = np.zeros_like(rewards)
    for b in range(rewards.shape[1]):
        next_advantage, next_value = 0.0, bootstrap[b]
        for t in reversed(range(rewards.shape[0])):
            delta = rewards[t, b] + discounts[t, b] * next_value - values[t, b]
            next_advantage = delta + discounts[t, b] * lam * next_advantage
            advantages[t, b] = next_advantage
            next_value = values[t, b]
    return advantages + values, advantages


def vtrace_reference(rewards, values, bootstrap, discounts, log_rhos, lam, rho_bar, c_bar, pg_rho_bar):
    """v_s = V(x_s) + sum_{t>=s} (prod_{s<=i<t} discount_i c_i) delta_t: the sum form, not the recursion."""
    n = rewards.shape[0]
    rhos = np.exp(log_rhos)
    next_values = np.concatenate([values[1:], bootstrap[None]])
    deltas = np.minimum(rho_bar, rhos) * (rewards + discounts * next_values - values)
    cs = lam * np.minimum(c_bar, rhos)
    vs = np.array(values, dtype=np.float64)
    for s in range(n):
        weight = np.ones(rewards.shape[1])
        for t in range(s, n):
            vs[s] += weight * deltas[t]
            weight = weight * discounts[t] * cs[t]
    next_vs = np.concatenate([vs[1:], bootstrap[None]])
    advantages = rewards + discounts * next_vs - values
    if pg_rho_bar is not None:
        advantages = np.minimum(pg_rho_bar, rhos) * advantages
    return vs, advantages


def discounted_returns(rewards, bootstrap, discounts):
    """n-step returns bootstrapped at the end: G_t = r_t + discount_t G_{t+1}, G_T = bootstrap."""
    returns = np.zeros_like(rewards)
    acc = bootstrap.copy()
    for t in reversed(range(rewards.shape[0])):
        acc = rewards[t] + discounts[t] * acc
        returns[t] = acc
    return returns


@pytest.mark.parametrize("lam", [0.0, 0.9, 1.0])
def test_gae_matches_loop(lam: float) -> None:
    rewards, values, bootstrap, discounts, _ = random_batch()
    targets, advantages = gae(*as_jax(rewards, values, bootstrap, discounts), lambda_=lam)
    ref_targets, ref_advantages = gae_reference(rewards, values, bootstrap, discounts, lam)
    np.testing.assert_allclose(advantages, ref_advantages, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(targets, ref_targets, rtol=1e-5, atol=1e-5)


def test_gae_lambda_one_is_discounted_return_minus_value() -> None:
    rewards, values, bootstrap, discounts, _ = random_batch(1)
    targets, advantages = gae(*as_jax(rewards, values, bootstrap, discounts), lambda_=1.0)
    returns = discounted_returns(rewards, bootstrap, discounts)
    np.testing.assert_allclose(targets, returns, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(advantages, returns - values, rtol=1e-5, atol=1e-5)


def test_gae_by_hand() -> None:
    # T = 3, one env, gamma 0.5, lambda 0.5, episode ends at step 1 (discount 0 there).
    rewards = jnp.array([[1.0], [2.0], [3.0]])
    values = jnp.array([[0.5], [1.0], [2.0]])
    discounts = jnp.array([[0.5], [0.0], [0.5]])
    bootstrap = jnp.array([4.0])
    # deltas: 1 + 0.5*1 - 0.5 = 1; 2 + 0 - 1 = 1; 3 + 0.5*4 - 2 = 3
    # A2 = 3; A1 = 1 + 0 * ... = 1; A0 = 1 + 0.5*0.5*1 = 1.25
    targets, advantages = gae(rewards, values, bootstrap, discounts, lambda_=0.5)
    np.testing.assert_allclose(advantages[:, 0], [1.25, 1.0, 3.0])
    np.testing.assert_allclose(targets[:, 0], [1.75, 2.0, 5.0])


def test_gae_done_stops_flow_across_episodes() -> None:
    rewards, values, bootstrap, discounts, _ = random_batch(2)
    targets, _ = gae(*as_jax(rewards, values, bootstrap, discounts), lambda_=0.9)
    later = rewards.copy()
    later[3:, 0] += 100.0  # step 2 of env 0 ends an episode: steps 0..2 must not see steps 3..
    later_targets, _ = gae(*as_jax(later, values, bootstrap, discounts), lambda_=0.9)
    np.testing.assert_allclose(later_targets[:3, 0], targets[:3, 0], rtol=1e-6)


@pytest.mark.parametrize(
    "lam, rho_bar, c_bar, pg_rho_bar", [(1.0, 1.0, 1.0, 1.0), (0.9, 1.0, 1.0, 1.0), (0.8, 2.0, 0.5, None)]
)
def test_vtrace_matches_sum_form(lam, rho_bar, c_bar, pg_rho_bar) -> None:
    rewards, values, bootstrap, discounts, log_rhos = random_batch(3)
    targets, advantages = vtrace(
        *as_jax(rewards, values, bootstrap, discounts, log_rhos),
        lambda_=lam,
        rho_bar=rho_bar,
        c_bar=c_bar,
        pg_rho_bar=pg_rho_bar,
    )
    ref_targets, ref_advantages = vtrace_reference(
        rewards, values, bootstrap, discounts, log_rhos, lam, rho_bar, c_bar, pg_rho_bar
    )
    np.testing.assert_allclose(targets, ref_targets, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(advantages, ref_advantages, rtol=1e-5, atol=1e-5)


def test_vtrace_on_policy_lambda_one_is_n_step_return() -> None:
    rewards, values, bootstrap, discounts, _ = random_batch(4)
    zeros = np.zeros_like(rewards)
    targets, advantages = vtrace(*as_jax(rewards, values, bootstrap, discounts, zeros), lambda_=1.0)
    returns = discounted_returns(rewards, bootstrap, discounts)
    np.testing.assert_allclose(targets, returns, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(advantages, returns - values, rtol=1e-5, atol=1e-5)
    _, gae_advantages = gae(*as_jax(rewards, values, bootstrap, discounts), lambda_=1.0)
    np.testing.assert_allclose(advantages, gae_advantages, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("lam", [0.5, 0.9])
def test_vtrace_on_policy_targets_are_gae_lambda_returns(lam: float) -> None:
    rewards, values, bootstrap, discounts, _ = random_batch(5)
    zeros = np.zeros_like(rewards)
    targets, _ = vtrace(*as_jax(rewards, values, bootstrap, discounts, zeros), lambda_=lam)
    gae_targets, _ = gae(*as_jax(rewards, values, bootstrap, discounts), lambda_=lam)
    np.testing.assert_allclose(targets, gae_targets, rtol=1e-5, atol=1e-5)


def test_vtrace_on_policy_advantages_skip_lambda_on_the_first_step() -> None:
    # On-policy the targets are GAE's, but IMPALA's advantage r_t + discount_t v_{t+1} - V(x_t) discounts the
    # tail after step t by discount_t alone, where GAE's discounts it by discount_t * lambda.
    rewards, values, bootstrap, discounts, _ = random_batch(6)
    zeros = np.zeros_like(rewards)
    _, advantages = vtrace(*as_jax(rewards, values, bootstrap, discounts, zeros), lambda_=0.9, pg_rho_bar=None)
    _, gae_advantages = gae_reference(rewards, values, bootstrap, discounts, 0.9)
    next_values = np.concatenate([values[1:], bootstrap[None]])
    deltas = rewards + discounts * next_values - values
    next_gae = np.concatenate([gae_advantages[1:], np.zeros((1, B))])
    np.testing.assert_allclose(advantages, deltas + discounts * next_gae, rtol=1e-5, atol=1e-5)
    assert np.abs(np.asarray(advantages) - gae_advantages).max() > 0.05


def test_vtrace_by_hand_with_clipping() -> None:
    # T = 2, one env, discount 1, lambda 1, rho_bar = c_bar = 1. rhos = (2, 0.5) -> clipped (1, 0.5).
    rewards = jnp.array([[1.0], [1.0]])
    values = jnp.array([[0.0], [1.0]])
    bootstrap = jnp.array([2.0])
    discounts = jnp.ones((2, 1))
    log_rhos = jnp.log(jnp.array([[2.0], [0.5]]))
    # delta1 = 0.5 * (1 + 2 - 1) = 1 -> v1 = 2; delta0 = 1 * (1 + 1 - 0) = 2 -> v0 = 0 + 2 + 1 * c0 (=1) * 1 = 3
    # advantages: rho_pg0 = 1: 1 + v1 - V0 = 3; rho_pg1 = 0.5: 0.5 * (1 + 2 - 1) = 1
    targets, advantages = vtrace(rewards, values, bootstrap, discounts, log_rhos, lambda_=1.0)
    np.testing.assert_allclose(targets[:, 0], [3.0, 2.0], rtol=1e-6)
    np.testing.assert_allclose(advantages[:, 0], [3.0, 1.0], rtol=1e-6)


def test_returns_jit_and_trailing_dims() -> None:
    rng = np.random.default_rng(6)
    shape = (5, 2, 3)
    rewards, values, log_rhos = (jnp.asarray(rng.normal(size=shape), jnp.float32) for _ in range(3))
    bootstrap = jnp.asarray(rng.normal(size=shape[1:]), jnp.float32)
    discounts = jnp.full(shape, 0.99)
    targets, advantages = jax.jit(vtrace)(rewards, values, bootstrap, discounts, log_rhos)
    assert targets.shape == advantages.shape == shape
    flat = vtrace(
        *(x.reshape(5, 6) for x in (rewards, values)),
        bootstrap.reshape(6),
        discounts.reshape(5, 6),
        log_rhos.reshape(5, 6),
    )
    np.testing.assert_allclose(targets.reshape(5, 6), flat[0], rtol=1e-5, atol=1e-6)
