"""Stale data is measured in policy versions and dropped beyond the configured limit."""

from __future__ import annotations

import jax.numpy as jnp

from learner.update import check_policy_lag


def test_lag_is_versions_behind_and_limit_is_inclusive():
    check = check_policy_lag(jnp.array([10, 8, 6, 5]), 10, max_policy_lag=4)
    assert check.lag.tolist() == [0, 2, 4, 5]
    assert check.accepted.tolist() == [True, True, True, False]
