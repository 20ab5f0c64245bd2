"""Index plumbing of the pair tables: how per-contact and per-joint values are laid out and how they reach bodies.

The solver stages (step.py) speak of contacts, phases and bodies; this module is the only place that knows the
slot layout behind them (pairs.py builds the tables):

- contact slots: point 0 of every polygon pair, point 1 of every polygon pair, circle-polygon, circle-circle;
  `point0_slots` picks each pair's first slot (what the task layer reads);
- phases: `by_phase` splits slot-ordered values into the solver's phases, `in_slot_order` joins them back;
- bodies: a contact's bodies are static (`phase_bodies`, `write_back`: gathers with constant indices), a joint's
  or a thruster's are data (`one_hot_rows` + `sum_onto_bodies`: a multiply-sum over bodies, which fuses on
  every backend where a data-dependent scatter would not).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.physics.pairs import PairTables

Array = jax.Array


def point0_slots(tables: PairTables) -> np.ndarray:
    """[num_pairs] the contact slot of each pair's point 0 (a polygon pair's first point, any other pair's only
    one), in pair order."""
    rr = tables.num_rr
    return np.concatenate([np.arange(rr), np.arange(2 * rr, tables.num_contacts)]).astype(int)


def by_phase(values: Array, tables: PairTables) -> list[Array]:
    """Slot-ordered values (leading axis K) split into the solver's phases."""
    return [values[phase] for phase in tables.phases]


def in_slot_order(per_phase: list[Array], tables: PairTables) -> Array:
    """The inverse of `by_phase`."""
    slot_order = np.argsort(np.concatenate(tables.phases))
    return jnp.concatenate(per_phase)[slot_order]


def phase_bodies(tables: PairTables) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per phase, the static body indices of sides a and b of its contacts (no body twice within a phase)."""
    return [(tables.contact_a[phase], tables.contact_b[phase]) for phase in tables.phases]


def write_back(values: Array, new_a: Array, new_b: Array, body_a: np.ndarray, body_b: np.ndarray) -> Array:
    """`values` (leading axis: bodies) with the rows of `body_a` replaced by `new_a` and of `body_b` by `new_b`;
    the bodies must be distinct (one phase). A single static gather from the concatenation, no scatter."""
    num_bodies = values.shape[0]
    source = np.arange(num_bodies)
    source[body_a] = num_bodies + np.arange(len(body_a))
    source[body_b] = num_bodies + len(body_a) + np.arange(len(body_b))
    return jnp.concatenate([values, new_a, new_b])[source]


def one_hot_rows(indices: np.ndarray | Array, num_bodies: int) -> np.ndarray | Array:
    """[k, num_bodies] weights that are 1 where row i's body is `indices[i]`: a constant for static indices
    (numpy), traced for indices that are scene data."""
    if isinstance(indices, np.ndarray):
        return (indices[:, None] == np.arange(num_bodies)[None, :]).astype(np.float32)
    return (indices[:, None] == jnp.arange(num_bodies)[None, :]).astype(jnp.float32)


def sum_onto_bodies(one_hot: Array, values: Array) -> Array:
    """Sum per-row values onto bodies: [k, N] x [k, ...] -> [N, ...].

    A multiply-sum rather than a matmul: it fuses with its neighbours and never runs in reduced precision (TF32).
    """
    expand = one_hot.reshape(one_hot.shape + (1,) * (values.ndim - 1))
    return (expand * values[:, None]).sum(axis=0)


def read_body(values: Array, weights: Array) -> Array:
    """The row of `values` (leading axis: bodies) that one-hot `weights` [N] pick."""
    return (weights.reshape((-1,) + (1,) * (values.ndim - 1)) * values).sum(axis=0)


def spread_to_bodies(weights: Array, delta: Array) -> Array:
    """`delta` placed on the body one-hot `weights` [N] pick, zeros elsewhere: [N, *delta.shape]."""
    return weights.reshape((-1,) + (1,) * delta.ndim) * delta
