"""Sequential-impulse contact constraints: per-step constants, warm start, and one Gauss-Seidel sweep.

Lever arms, effective masses, friction coefficient, bias and restitution target are computed once per step, which
keeps the sweep cheap. Jax2D recomputes lever arms and effective masses at every visit from the current
positions, which the joints' position projection moves during the iterations. That is not a negligible
difference on articulated levels: measured against Jax2D it parts some of them by tens of centimetres within
two seconds (benchmarks/RESULTS.md). `solver="jax2d"` (batched_contacts.py) recomputes them as Jax2D does.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from impulse.engine.physics.geometry import cross, cross_scalar_vector, dot, nonzero
from impulse.engine.physics.narrowphase import Contacts
from impulse.engine.physics.pairs import PairTables
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.slots import one_hot_rows, sum_onto_bodies, write_back
from impulse.engine.physics.state import SimState

Array = jnp.ndarray


class ContactRows(NamedTuple):
    """Solver constants for a set of contacts (all slots, or one phase's slots)."""

    normal: Array  # [k, 2]
    tangent: Array  # [k, 2]
    lever_a: Array  # [k, 2] contact point minus a's centre of mass
    lever_b: Array  # [k, 2]
    inverse_mass_a: Array  # [k]
    inverse_mass_b: Array
    inverse_inertia_a: Array
    inverse_inertia_b: Array
    normal_mass: Array  # [k] 1 / effective mass along the normal, 0 for contacts that must not act
    tangent_mass: Array  # [k]
    friction: Array  # [k] combined coefficient
    target_velocity: Array  # [k] desired normal velocity: position bias minus restitution bounce


def contact_rows(
    state: SimState,
    velocity: Array,
    contacts: Contacts,
    tables: PairTables,
    params: SimParams,
) -> tuple[ContactRows, Array]:
    """Constants of every contact slot, and which slots may exchange impulses this step."""
    bodies = state.bodies
    a, b = tables.contact_a, tables.contact_b
    ima, imb = bodies.inverse_mass[a], bodies.inverse_mass[b]
    iia, iib = bodies.inverse_inertia[a], bodies.inverse_inertia[b]
    n = contacts.normal
    t = jnp.stack([n[:, 1], -n[:, 0]], axis=-1)
    lever_a = contacts.point - bodies.position[a]
    lever_b = contacts.point - bodies.position[b]
    enabled = contacts.touching & state.pair_collides[tables.contact_pair] & ~((ima == 0) & (imb == 0))

    def inverse_effective_mass(direction: Array) -> Array:
        k = ima + imb + iia * cross(lever_a, direction) ** 2 + iib * cross(lever_b, direction) ** 2
        return jnp.where(enabled, 1.0 / nonzero(k), 0.0)

    base = params.base_friction
    friction = jnp.sqrt((base * bodies.friction[a]) ** 2 + (base * bodies.friction[b]) ** 2)
    w = bodies.angular_velocity
    relative = (velocity[b] + cross_scalar_vector(w[b], lever_b)) - (
        velocity[a] + cross_scalar_vector(w[a], lever_a)
    )
    bounce = jnp.minimum(bodies.restitution[a], bodies.restitution[b]) * dot(relative, n)
    bias = params.baumgarte_coefficient_collision / params.dt * jnp.maximum(
        contacts.penetration - params.slop, 0.0
    )
    rows = ContactRows(
        normal=n,
        tangent=t,
        lever_a=lever_a,
        lever_b=lever_b,
        inverse_mass_a=ima,
        inverse_mass_b=imb,
        inverse_inertia_a=iia,
        inverse_inertia_b=iib,
        normal_mass=inverse_effective_mass(n),
        tangent_mass=inverse_effective_mass(t),
        friction=friction,
        target_velocity=bias - bounce,
    )
    return rows, enabled


def warm_start(
    velocity: Array,
    angular_velocity: Array,
    rows: ContactRows,
    normal_impulse: Array,
    tangent_impulse: Array,
    tables: PairTables,
) -> tuple[Array, Array]:
    """Apply last step's impulses of all contacts at once (they do not depend on velocity, so order is moot)."""
    impulse = normal_impulse[:, None] * rows.normal + tangent_impulse[:, None] * rows.tangent
    num_bodies = velocity.shape[0]
    to_a, to_b = one_hot_rows(tables.contact_a, num_bodies), one_hot_rows(tables.contact_b, num_bodies)
    dv = rows.inverse_mass_b[:, None] * impulse
    dv_a = -rows.inverse_mass_a[:, None] * impulse
    dw_a = -rows.inverse_inertia_a * cross(rows.lever_a, impulse)
    dw_b = rows.inverse_inertia_b * cross(rows.lever_b, impulse)
    velocity = velocity + sum_onto_bodies(to_a, dv_a) + sum_onto_bodies(to_b, dv)
    angular_velocity = angular_velocity + sum_onto_bodies(to_a, dw_a) + sum_onto_bodies(to_b, dw_b)
    return velocity, angular_velocity


def solve_phase(
    velocity: Array,
    angular_velocity: Array,
    rows: ContactRows,
    body_a: np.ndarray,
    body_b: np.ndarray,
    normal_impulse: Array,
    tangent_impulse: Array,
) -> tuple[Array, Array, Array, Array]:
    """One sequential-impulse visit of contacts that share no body, solved side by side."""
    va, vb = velocity[body_a], velocity[body_b]
    wa, wb = angular_velocity[body_a], angular_velocity[body_b]

    def relative_velocity() -> Array:
        return (vb + cross_scalar_vector(wb, rows.lever_b)) - (va + cross_scalar_vector(wa, rows.lever_a))

    def apply(impulse: Array) -> tuple[Array, Array, Array, Array]:
        return (
            va - rows.inverse_mass_a[:, None] * impulse,
            wa - rows.inverse_inertia_a * cross(rows.lever_a, impulse),
            vb + rows.inverse_mass_b[:, None] * impulse,
            wb + rows.inverse_inertia_b * cross(rows.lever_b, impulse),
        )

    normal_speed = dot(relative_velocity(), rows.normal)
    new_normal = jnp.maximum(normal_impulse + (rows.target_velocity - normal_speed) * rows.normal_mass, 0.0)
    va, wa, vb, wb = apply((new_normal - normal_impulse)[:, None] * rows.normal)

    tangent_speed = dot(relative_velocity(), rows.tangent)
    limit = rows.friction * new_normal
    new_tangent = jnp.clip(tangent_impulse - tangent_speed * rows.tangent_mass, -limit, limit)
    va, wa, vb, wb = apply((new_tangent - tangent_impulse)[:, None] * rows.tangent)

    velocity = write_back(velocity, va, vb, body_a, body_b)
    angular_velocity = write_back(angular_velocity, wa, wb, body_a, body_b)
    return velocity, angular_velocity, new_normal, new_tangent
