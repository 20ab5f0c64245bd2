"""Kinetix's reward, per physics sub-step, over the engine's static pair table.

- Effective role of a body = role x active (inactive bodies count as neutral). A pair whose effective roles
  multiply to 2 is green-blue (goal), to 3 green-red (death); other products mean nothing.
- Sparse reward of a sub-step: -1 if any green-red pair is touching, else +1 if any green-blue pair is, else 0.
  "Touching" is the engine's `StepContacts.touching`: geometric overlap of active bodies whose collision modes
  meet, regardless of joints (a jointed green-blue pair that overlaps counts), as Kinetix reads its manifolds.
- Distance (for dense shaping) = sum over all green-blue pairs of the distance between the two centres of mass.

The pair classes depend only on roles and active flags, which physics never changes, so they are computed once
per agent step and reused by every sub-step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.levels.level import Level
from impulse.engine.physics.pairs import PairTables
from impulse.engine.physics.state import SimState

Array = jax.Array

GOAL_PRODUCT = 2  # green (1) x blue (2)
DEATH_PRODUCT = 3  # green (1) x red (3)


class PairRoles(NamedTuple):
    goal: Array  # [num_pairs] bool: green-blue pair
    death: Array  # [num_pairs] bool: green-red pair


def pair_roles(sim: SimState, level: Level, tables: PairTables) -> PairRoles:
    effective = level.roles * sim.bodies.active.astype(level.roles.dtype)
    product = effective[tables.pair_a] * effective[tables.pair_b]
    return PairRoles(goal=product == GOAL_PRODUCT, death=product == DEATH_PRODUCT)


def sparse_reward(touching: Array, roles: PairRoles) -> Array:
    """-1.0, +1.0 or 0.0 for one sub-step's contacts."""
    death = jnp.any(touching & roles.death)
    goal = jnp.any(touching & roles.goal)
    return jnp.where(death, -1.0, jnp.where(goal, 1.0, 0.0)).astype(jnp.float32)


def goal_distance(position: Array, roles: PairRoles, tables: PairTables) -> Array:
    """Sum of centre distances over green-blue pairs (0 when there is none)."""
    offset = position[tables.pair_a] - position[tables.pair_b]
    distance = jnp.sqrt(offset[:, 0] ** 2 + offset[:, 1] ** 2)
    return jnp.sum(jnp.where(roles.goal, distance, 0.0))


def dense_reward(distance: Array, last_distance: Array, scale: Array, unset: float) -> Array:
    """-(distance - last_distance) * scale; 0 right after a reset (last_distance unset) and for non-finite
    deltas."""
    delta = -(distance - last_distance) * scale
    delta = jnp.where(jnp.isfinite(delta), delta, 0.0)
    return jnp.where(last_distance == unset, 0.0, delta)
