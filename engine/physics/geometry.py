"""2D vector helpers on arrays whose last axis holds (x, y), and `VectorOps`: the vector algebra a solver visit is
written against, so that one visit serves these arrays (the XLA step, `ARRAYS`) and the kernel's lanes, where a
vector is a pair of rows (`lanes.LANES`)."""

from __future__ import annotations

import operator
from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp

Array = jnp.ndarray


class VectorOps(NamedTuple):
    """The operations on 2D vectors (V) and scalars (S) a solver visit uses, for one way of holding vectors."""

    add: Callable[[Any, Any], Any]  # V + V
    sub: Callable[[Any, Any], Any]  # V - V
    scale: Callable[[Any, Any], Any]  # S * V
    dot: Callable[[Any, Any], Any]  # V . V -> S
    cross: Callable[[Any, Any], Any]  # V x V -> S
    spin: Callable[[Any, Any], Any]  # S x V: the velocity of a point at lever V on a body spinning at S


def cross(a: Array, b: Array) -> Array:
    """Scalar cross product a x b."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def cross_scalar_vector(s: Array, v: Array) -> Array:
    """s x v: the velocity of a point at lever arm v on a body spinning at angular velocity s."""
    return jnp.stack([-s * v[..., 1], s * v[..., 0]], axis=-1)


def dot(a: Array, b: Array) -> Array:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def rotate(angle: Array, v: Array) -> Array:
    """Rotate v by `angle` (broadcast over leading axes)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def nonzero(x: Array) -> Array:
    """x, or 1 where x == 0: the divide guard Jax2D applies to every denominator (masked slots stay finite)."""
    return jnp.where(x == 0, 1.0, x)


def length(v: Array) -> Array:
    return jnp.sqrt(dot(v, v))


def scale(s: Array, v: Array) -> Array:
    """s * v for a scalar per vector (s has v's leading axes)."""
    return s[..., None] * v


ARRAYS = VectorOps(add=operator.add, sub=operator.sub, scale=scale, dot=dot, cross=cross, spin=cross_scalar_vector)
"""`VectorOps` on arrays whose last axis holds (x, y)."""
