"""Action distributions of the three Kinetix action types, as pure functions of a parameter array.

A distribution here is a small frozen description (sizes only) whose methods take the network's output array
`params` [..., num_params] and work over any leading dimensions:

- `MultiCategorical(nvec)`: independent categoricals laid end to end in the logits (Kinetix's multi-discrete:
  nvec (3, 3, 3, 3, 2, 2), 16 logits); actions int32 [..., len(nvec)]; log-probabilities and entropies are
  summed over the dimensions.
- `Categorical(n)`: one categorical (Kinetix's discrete: 11 logits); actions int32 [...].
- `DiagGaussian(dim)`: a diagonal Gaussian; `params` is the mean followed by the log standard deviation,
  [..., 2 * dim] (the network keeps the log-std state-independent and broadcasts it); actions float32 [..., dim].
  Samples are not squashed or clipped: the environment clips them.

`sample(params, key)`, `log_prob(params, action)`, `entropy(params)` and `mode(params)` are all jit-friendly;
`distribution_for(space)` picks the one matching an `engine.env.actions.ActionSpace`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.env.actions import ActionSpace

Array = jax.Array


def _categorical_log_prob(logits: Array, action: Array) -> Array:
    log_p = jax.nn.log_softmax(logits, axis=-1)
    return jnp.take_along_axis(log_p, action[..., None].astype(jnp.int32), axis=-1)[..., 0]


def _categorical_entropy(logits: Array) -> Array:
    log_p = jax.nn.log_softmax(logits, axis=-1)
    # A value with probability 0 (a -inf logit) contributes 0 * log 0 = 0; taking log 0 as 0 keeps both the
    # value and its gradient finite (exp(-inf) * -inf would be nan).
    finite_log_p = jnp.where(jnp.isfinite(log_p), log_p, 0.0)
    return -jnp.sum(jnp.exp(log_p) * finite_log_p, axis=-1)


@dataclass(frozen=True)
class Categorical:
    """One categorical over `n` values; `params` are its logits [..., n]."""

    n: int

    @property
    def num_params(self) -> int:
        return self.n

    def sample(self, params: Array, key: Array) -> Array:
        return jax.random.categorical(key, params, axis=-1).astype(jnp.int32)

    def log_prob(self, params: Array, action: Array) -> Array:
        return _categorical_log_prob(params, action)

    def entropy(self, params: Array) -> Array:
        return _categorical_entropy(params)

    def mode(self, params: Array) -> Array:
        return jnp.argmax(params, axis=-1).astype(jnp.int32)


@dataclass(frozen=True)
class MultiCategorical:
    """Independent categoricals with `nvec[i]` values each; `params` are all their logits end to end
    [..., sum(nvec)], dimension 0 first. Dimensions are padded to the largest size with -inf logits so that all
    are handled as one [..., D, max(nvec)] array."""

    nvec: tuple[int, ...]

    @property
    def num_params(self) -> int:
        return sum(self.nvec)

    def _logits(self, params: Array) -> Array:
        """[..., D, K] logits, K = max(nvec), padding entries -inf."""
        width = max(self.nvec)
        starts = np.cumsum((0,) + self.nvec[:-1])
        # Gather index table [D, K] into params; padding points at a column that is then masked out.
        index = np.array([[s + min(k, n - 1) for k in range(width)] for s, n in zip(starts, self.nvec)])
        valid = np.array([[k < n for k in range(width)] for n in self.nvec])
        logits = params[..., index]
        return jnp.where(valid, logits, -jnp.inf)

    def sample(self, params: Array, key: Array) -> Array:
        return jax.random.categorical(key, self._logits(params), axis=-1).astype(jnp.int32)

    def log_prob(self, params: Array, action: Array) -> Array:
        return jnp.sum(_categorical_log_prob(self._logits(params), action), axis=-1)

    def entropy(self, params: Array) -> Array:
        return jnp.sum(_categorical_entropy(self._logits(params)), axis=-1)

    def mode(self, params: Array) -> Array:
        return jnp.argmax(self._logits(params), axis=-1).astype(jnp.int32)


@dataclass(frozen=True)
class DiagGaussian:
    """A Gaussian with independent dimensions; `params` = [mean, log_std] along the last axis [..., 2 * dim]."""

    dim: int

    @property
    def num_params(self) -> int:
        return 2 * self.dim

    def _split(self, params: Array) -> tuple[Array, Array]:
        return params[..., : self.dim], params[..., self.dim :]

    def sample(self, params: Array, key: Array) -> Array:
        mean, log_std = self._split(params)
        return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)

    def log_prob(self, params: Array, action: Array) -> Array:
        mean, log_std = self._split(params)
        z = (action - mean) * jnp.exp(-log_std)
        return jnp.sum(-0.5 * z**2 - log_std - 0.5 * math.log(2 * math.pi), axis=-1)

    def entropy(self, params: Array) -> Array:
        _, log_std = self._split(params)
        return jnp.sum(log_std + 0.5 * (1.0 + math.log(2 * math.pi)), axis=-1)

    def mode(self, params: Array) -> Array:
        return self._split(params)[0]


Distribution = Categorical | MultiCategorical | DiagGaussian


def distribution_for(space: ActionSpace) -> Distribution:
    """The distribution a policy needs for an action space (`engine.env.actions.action_space(spec)`)."""
    if space.kind == "multi_discrete":
        return MultiCategorical(tuple(space.nvec))
    if space.kind == "discrete":
        return Categorical(space.nvec[0])
    if space.kind == "continuous":
        return DiagGaussian(int(np.prod(space.shape)))
    raise ValueError(f"unknown action space kind {space.kind!r}")
