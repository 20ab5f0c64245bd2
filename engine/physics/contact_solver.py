"""Sequential-impulse contact constraints: per-step constants, warm start, and one Gauss-Seidel sweep.

Lever arms, effective masses, friction coefficient, bias and restitution target are computed once per step, which
keeps the sweep cheap. Jax2D recomputes lever arms and effective masses at every visit from the current
positions, which the joints' position projection moves during the iterations. That is not a negligible
difference on articulated levels: measured against Jax2D it parts some of them by tens of centimetres within
two seconds (benchmarks/RESULTS.md). `solver="jax2d"` (batched_contacts.py) recomputes them as Jax2D does.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from impulse.engine.physics.geometry import ARRAYS, VectorOps, cross, cross_scalar_vector, dot, nonzero
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
    """One sequential-impulse visit of contacts that share no body, solved side by side (`visit_contact` on
    arrays)."""
    va, vb = velocity[body_a], velocity[body_b]
    wa, wb = angular_velocity[body_a], angular_velocity[body_b]
    va, wa, vb, wb, new_normal, new_tangent = visit_contact(ARRAYS, rows, va, wa, vb, wb, normal_impulse,
                                                            tangent_impulse)
    velocity = write_back(velocity, va, vb, body_a, body_b)
    angular_velocity = write_back(angular_velocity, wa, wb, body_a, body_b)
    return velocity, angular_velocity, new_normal, new_tangent


def visit_contact(ops: VectorOps, c: Any, va: Any, wa: Any, vb: Any, wb: Any, normal_impulse: Any,
                  tangent_impulse: Any) -> tuple[Any, Any, Any, Any, Any, Any]:
    """The contact visit, written once for every schedule that keeps constants per step: the normal impulse, then
    friction, from the velocities and spins of the contacts' bodies (a, b) and their accumulated impulses; returns
    the bodies' new velocities and spins and the new impulses. `c` holds the contacts' `ContactRows`; `ops` says
    how vectors are held: `geometry.ARRAYS` for [k, 2] arrays (`solve_phase`, k contacts side by side), `lanes.LANES`
    for pairs of rows (the kernel, one contact on every lane)."""

    def relative_velocity() -> Any:
        return ops.sub(ops.add(vb, ops.spin(wb, c.lever_b)), ops.add(va, ops.spin(wa, c.lever_a)))

    def apply(impulse: Any) -> tuple[Any, Any, Any, Any]:
        return (
            ops.sub(va, ops.scale(c.inverse_mass_a, impulse)), wa - c.inverse_inertia_a * ops.cross(c.lever_a, impulse),
            ops.add(vb, ops.scale(c.inverse_mass_b, impulse)), wb + c.inverse_inertia_b * ops.cross(c.lever_b, impulse),
        )

    normal_speed = ops.dot(relative_velocity(), c.normal)
    new_normal = jnp.maximum(normal_impulse + (c.target_velocity - normal_speed) * c.normal_mass, 0.0)
    va, wa, vb, wb = apply(ops.scale(new_normal - normal_impulse, c.normal))

    tangent_speed = ops.dot(relative_velocity(), c.tangent)
    limit = c.friction * new_normal
    new_tangent = jnp.clip(tangent_impulse - tangent_speed * c.tangent_mass, -limit, limit)
    va, wa, vb, wb = apply(ops.scale(new_tangent - tangent_impulse, c.tangent))
    return va, wa, vb, wb, new_normal, new_tangent
