"""Contact solve in Jax2D's schedule: the `schedule="jax2d"` solver option of the step.

Why it exists: our default schedule (phased Gauss-Seidel, constants fixed per step, see contact_solver.py) is
faster but visits contacts in another order, and on articulated levels that order difference grows into
centimetres within a couple of seconds. This schedule reproduces Jax2D 1.0.2's order so that trajectories can be
matched where that matters:

- per iteration, contacts are visited kind by kind: polygon pairs' point 0, polygon pairs' point 1,
  circle-polygon, circle-circle;
- within a kind, pairs are ordered touching-last (a stable sort on the touching flag; for polygon pairs, either
  point touching), the list is padded to a multiple of `BATCH` and dealt round-robin into batches of `BATCH`;
- batches run one after another; the contacts of one batch are solved from the same velocities (Jacobi) and
  their velocity changes are summed;
- lever arms and effective masses are recomputed at every visit from the current positions, which the joint
  pass moves during the iterations.

That is why its visit (`solve_batch`) is its own and not `contact_solver.visit_contact`, which the default schedule
and the fused kernel share: Jax2D's order of operations (dividing by the effective mass at each visit, summing a
batch's changes) is what this schedule exists to reproduce.

Padding slots do nothing here by default. Jax2D's padding also overwrites the accumulated impulse of each kind's
last pair (bug B1 of the Jax2D digest): its padded slots carry index -1, which wraps onto that pair, and write it a
zero in every batch that holds padding. We do not copy that into "jax2d"; `schedule="jax2d_wipe"` reproduces it, off
the default path, so that trajectories can be compared with Jax2D's and Kinetix's on the levels it changes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.physics.context import Impulses, StepContext
from impulse.engine.physics.geometry import cross_scalar_vector, dot, nonzero
from impulse.engine.physics.joint_solver import JointSolverState
from impulse.engine.physics.pairs import PairTables

Array = jax.Array

BATCH = 16  # Jax2D's default solver_batch_size, which Kinetix keeps


class KindBatches(NamedTuple):
    """One contact kind's visits in Jax2D's order."""

    slots: Array  # [num_batches, BATCH] contact slots; padding is the out-of-range slot K
    wiped: Array  # [num_batches] the slot whose impulses Jax2D's padding zeroes after the batch, or K for none


def batch_slots(tables: PairTables, touching: Array, wipe: bool = False) -> list[KindBatches]:
    """Per kind, the contact slots to visit in Jax2D's order; padding reads are clamped and masked, its writes
    dropped. With `wipe`, each batch that holds padding also names the kind's last slot, whose impulses the
    batch then zeroes (bug B1); which batches hold padding depends on the counts only, so it is static."""
    num_contacts = tables.num_contacts
    kinds = []
    rr, cr, cc = tables.num_rr, tables.num_cr, tables.num_cc
    if rr:
        either = touching[:rr] | touching[rr:2 * rr]
        kinds += [(either, 0, rr), (either, rr, rr)]
    if cr:
        kinds.append((touching[2 * rr:2 * rr + cr], 2 * rr, cr))
    if cc:
        kinds.append((touching[2 * rr + cr:], 2 * rr + cr, cc))
    out = []
    for active, first, count in kinds:
        num_batches = math.ceil(count / BATCH)
        order = jnp.argsort(active, stable=True).astype(jnp.int32) + first
        padded = jnp.concatenate([order, jnp.full(num_batches * BATCH - count, num_contacts, jnp.int32)])
        slots = padded.reshape(BATCH, num_batches).T
        padded_batches = [(BATCH - 1) * num_batches + j >= count for j in range(num_batches)]
        last = first + count - 1
        wiped = [last if wipe and has_padding else num_contacts for has_padding in padded_batches]
        out.append(KindBatches(slots, jnp.asarray(wiped, jnp.int32)))
    return out


def solve_batch(
    position: Array,
    velocity: Array,
    angular_velocity: Array,
    impulses: Impulses,
    slots: Array,
    context: StepContext,
) -> tuple[Array, Array, Impulses]:
    """One Jacobi batch: every slot in `slots` reads the same velocities; the changes are summed onto bodies.
    Lever arms and effective masses come from `position`, the bodies' current positions."""
    tables = context.tables
    num_contacts = tables.num_contacts
    real = slots < num_contacts
    k = jnp.minimum(slots, num_contacts - 1)
    a = jnp.asarray(tables.contact_a)[k]
    b = jnp.asarray(tables.contact_b)[k]
    c = context.contact_rows
    on = real & context.enabled[k]
    n, t = c.normal[k], c.tangent[k]
    ima, imb = c.inverse_mass_a[k], c.inverse_mass_b[k]
    iia, iib = c.inverse_inertia_a[k], c.inverse_inertia_b[k]
    point = context.contacts.point[k]
    ra = point - position[a]
    rb = point - position[b]
    va, vb = velocity[a], velocity[b]
    wa, wb = angular_velocity[a], angular_velocity[b]
    lam_n, lam_t = impulses.normal[k], impulses.tangent[k]

    def inverse_effective_mass(direction: Array) -> Array:
        ra_n, rb_n = dot(ra, direction), dot(rb, direction)
        return ima + imb + iia * (dot(ra, ra) - ra_n * ra_n) + iib * (dot(rb, rb) - rb_n * rb_n)

    def relative(va: Array, wa: Array, vb: Array, wb: Array) -> Array:
        return (vb + cross_scalar_vector(wb, rb)) - (va + cross_scalar_vector(wa, ra))

    def turn(r: Array, impulse: Array) -> Array:
        return r[:, 0] * impulse[:, 1] - r[:, 1] * impulse[:, 0]

    speed_n = dot(relative(va, wa, vb, wb), n)
    new_n = jnp.maximum(lam_n + (c.target_velocity[k] - speed_n) / nonzero(inverse_effective_mass(n)), 0.0)
    p_n = (new_n - lam_n)[:, None] * n
    dva, dvb = -ima[:, None] * p_n, imb[:, None] * p_n
    dwa, dwb = -iia * turn(ra, p_n), iib * turn(rb, p_n)

    speed_t = dot(relative(va + dva, wa + dwa, vb + dvb, wb + dwb), t)
    limit = c.friction[k] * new_n
    new_t = jnp.clip(lam_t - speed_t / nonzero(inverse_effective_mass(t)), -limit, limit)
    p_t = (new_t - lam_t)[:, None] * t
    dva, dvb = dva - ima[:, None] * p_t, dvb + imb[:, None] * p_t
    dwa, dwb = dwa - iia * turn(ra, p_t), dwb + iib * turn(rb, p_t)

    mask = on.astype(velocity.dtype)
    velocity = velocity.at[a].add(dva * mask[:, None]).at[b].add(dvb * mask[:, None])
    angular_velocity = angular_velocity.at[a].add(dwa * mask).at[b].add(dwb * mask)
    return velocity, angular_velocity, Impulses(
        normal=impulses.normal.at[slots].set(jnp.where(on, new_n, 0.0), mode="drop"),
        tangent=impulses.tangent.at[slots].set(jnp.where(on, new_t, 0.0), mode="drop"),
    )


def solve_contacts(
    joint_state: JointSolverState, impulses: Impulses, batches: list[KindBatches], context: StepContext
) -> tuple[JointSolverState, Impulses]:
    """One iteration's contact sweep, kind after kind, batch after batch; with the "jax2d_wipe" schedule, each
    batch ends with Jax2D's padding write onto its `wiped` slot."""
    wipe = context.options.schedule == "jax2d_wipe"
    position = joint_state.position
    velocity, angular_velocity = joint_state.velocity, joint_state.angular_velocity
    for kind in batches:
        def visit(carry: tuple[Array, Array, Impulses], batch: KindBatches) -> tuple:
            velocity, angular_velocity, impulses = solve_batch(position, *carry, batch.slots, context)
            if wipe:
                impulses = Impulses(
                    normal=impulses.normal.at[batch.wiped].set(0.0, mode="drop"),
                    tangent=impulses.tangent.at[batch.wiped].set(0.0, mode="drop"),
                )
            return (velocity, angular_velocity, impulses), None

        carry = (velocity, angular_velocity, impulses)
        if kind.slots.shape[0] == 1:
            carry = visit(carry, KindBatches(kind.slots[0], kind.wiped[0]))[0]
        else:
            carry, _ = jax.lax.scan(visit, carry, kind)
        velocity, angular_velocity, impulses = carry
    return joint_state._replace(velocity=velocity, angular_velocity=angular_velocity), impulses
