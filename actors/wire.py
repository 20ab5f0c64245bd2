"""How the actor-learner types travel on the bus: pytrees as flat named arrays, and the schemas that check them.

This is the one place that knows the wire layout of a `TrajectoryBatch` and of the policy weights. A pytree
becomes `{name: array}` with names made from its paths (`steps/obs/polygons`, `params/actor/dense_0/kernel`; see
`engine.pytree.tree_arrays`), and is rebuilt in the order of a template of the same structure, which both
ends derive from the same config. Receivers check every message against a schema made from that template (exact
shapes, dtypes and finiteness) before it reaches a jitted function, so a foreign or corrupt message is refused
at the door instead of crashing or recompiling one.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
from impulse.actors.trajectory import TrajectoryBatch
from impulse.bus.codec import Kind, Message, tree_hash
from impulse.bus.schema import ArraySpec, Schema, check
from impulse.engine.pytree import path_name, tree_from_arrays

TRAJECTORY_FINITE = ("steps/obs", "steps/log_prob", "steps/value", "steps/reward", "steps/episode_return",
                     "bootstrap_obs")
"""Float arrays of a trajectory that must hold no NaN or Inf (a NaN reward would poison the update)."""


def _specs(template: Any, finite: tuple[str, ...] | bool) -> dict[str, ArraySpec]:
    specs = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(template)[0]:
        name = path_name(path)
        is_finite = finite if isinstance(finite, bool) else any(name == f or name.startswith(f + "/") for f in finite)
        specs[name] = ArraySpec(np.dtype(leaf.dtype), tuple(leaf.shape), is_finite)
    return specs


def trajectory_schema(template: TrajectoryBatch) -> Schema:
    """Exactly the batch shapes the learner's update was compiled for."""
    return Schema(Kind.TRAJECTORY, _specs(template, TRAJECTORY_FINITE))


def weights_hash(params: Any) -> str:
    """Names, dtypes and shapes of the parameters: an actor refuses weights of another network by it."""
    return tree_hash({name: _shape_only(leaf) for name, leaf in _named_leaves(params)})


def _named_leaves(tree: Any) -> list[tuple[str, Any]]:
    return [(path_name(path), leaf) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]]


def _shape_only(leaf: Any) -> np.ndarray:
    """A zero-stride array with the leaf's dtype and shape: `tree_hash` reads only those."""
    return np.lib.stride_tricks.as_strided(np.zeros((), leaf.dtype), shape=leaf.shape, strides=(0,) * len(leaf.shape))


def weights_schema(params_template: Any) -> Schema:
    """The weights of this network: exact shapes, finite values, matching tree hash."""
    return Schema(Kind.WEIGHTS, _specs(params_template, True), tree_hash=weights_hash(params_template))


def checked_tree(message: Message, schema: Schema, template: Any) -> Any:
    """The pytree a message carries, after checking it against `schema` (raises `bus.codec.Rejected` if not)."""
    check(message, schema)
    return tree_from_arrays(message.arrays, template)

