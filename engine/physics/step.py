"""One physics step of one scene: `step(state, params, actions, sizes)`; jit it with `sizes` static, vmap it over
scenes.

Order (Jax2D's): gravity; contact detection; motors; thrusters; warm start; `num_solver_iterations` sweeps of
(joints in slot order, then contacts); symplectic Euler integration; clamping. `sizes.solver` picks how contacts
are swept: phase by phase with per-step lever arms ("phased", the default, faster) or as Jax2D does, in sorted
Jacobi batches with lever arms that follow the joints' position corrections ("jax2d", see docs/engine.md).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from engine.physics.actuators import apply_motors, apply_thrusters, thruster_positions
from engine.physics.batched_contacts import ContactConstants, batch_slots, solve_contacts
from engine.physics.contact_solver import ContactRows, contact_rows, solve_phase, warm_start
from engine.physics.joint_solver import JointRows, JointSolverState, joint_rows, solve_joint, warm_start_joints
from engine.physics.narrowphase import Contacts, detect_contacts
from engine.physics.pairs import PairTables, pair_tables
from engine.physics.params import SimParams
from engine.physics.sizes import SceneSizes
from engine.physics.state import ContactCache, Joints, SimState

Array = jax.Array


class StepContacts(NamedTuple):
    """What the task layer needs to know about touching shapes after a step, one entry per pair
    (see `pairs.pair_tables(sizes).pair_a / pair_b` for the bodies of each pair)."""

    touching: Array  # [num_pairs] bool: geometric overlap (point 0), joints notwithstanding, as Kinetix reads it
    normal: Array  # [num_pairs, 2]
    point: Array  # [num_pairs, 2]
    normal_impulse: Array  # [num_pairs] accumulated normal impulse of point 0


@functools.partial(jax.jit, static_argnames="sizes")
def jit_step(state: SimState, params: SimParams, actions: Array, sizes: SceneSizes):
    return step(state, params, actions, sizes)


def step(
    state: SimState, params: SimParams, actions: Array, sizes: SceneSizes
) -> tuple[SimState, StepContacts]:
    """Advance one scene by params.dt.

    `actions` has num_joints motor actions (Kinetix clips them to [-1, 1]) followed by num_thrusters thruster
    actions ([0, 1]).
    """
    tables = pair_tables(sizes)
    bodies = state.bodies
    num_joints = sizes.num_joints
    actions = jnp.asarray(actions, dtype=jnp.float32)
    motor_actions, thruster_actions = actions[:num_joints], actions[num_joints:]

    falls = (bodies.inverse_mass != 0) & bodies.active
    velocity = bodies.velocity + jnp.where(falls[:, None], state.gravity * params.dt, 0.0)
    angular_velocity = bodies.angular_velocity

    contacts = detect_contacts(state, tables)
    rows, enabled = contact_rows(state, velocity, contacts, tables, params)
    carried = enabled & state.contacts.active & sizes.warm_starting
    normal_impulse = jnp.where(carried, state.contacts.normal_impulse, 0.0)
    tangent_impulse = jnp.where(carried, state.contacts.tangent_impulse, 0.0)

    jrows = joint_rows(state)
    angular_velocity = apply_motors(angular_velocity, state, jrows, motor_actions, params)
    velocity, angular_velocity = apply_thrusters(velocity, angular_velocity, state, thruster_actions, params)

    joints = state.joints
    if sizes.warm_starting:
        velocity, angular_velocity = warm_start(
            velocity, angular_velocity, rows, normal_impulse, tangent_impulse, tables
        )
        velocity, angular_velocity = warm_start_joints(velocity, angular_velocity, jrows, joints)
        acc_impulse, acc_r_impulse = joints.acc_impulse, joints.acc_r_impulse
    else:
        acc_impulse, acc_r_impulse = jnp.zeros_like(joints.acc_impulse), jnp.zeros_like(joints.acc_r_impulse)

    start = JointSolverState(
        position=bodies.position,
        velocity=velocity,
        angular_velocity=angular_velocity,
        acc_impulse=acc_impulse,
        acc_r_impulse=acc_r_impulse,
        anchor=joints.global_position,
    )
    if sizes.solver == "jax2d":
        solved, normal_impulse, tangent_impulse = _iterate_jax2d(
            start, normal_impulse, tangent_impulse, contacts, rows, enabled, jrows, joints, params, sizes, tables
        )
    else:
        solved, normal_impulse, tangent_impulse = _iterate_phased(
            start, normal_impulse, tangent_impulse, rows, jrows, joints, params, sizes, tables
        )

    num_contacts = tables.num_contacts
    velocity = jnp.clip(solved.velocity, -params.clip_velocity, params.clip_velocity)
    angular_velocity = jnp.clip(solved.angular_velocity, -params.clip_angular_velocity, params.clip_angular_velocity)
    # Integrate with the clamped velocities (Jax2D integrates first): a body pinned at the position clamp by a
    # joint otherwise gains unbounded spin and ends in NaN.
    position = solved.position + velocity * params.dt
    rotation = bodies.rotation + angular_velocity * params.dt
    position = jnp.clip(position, -params.clip_position, params.clip_position)

    new_bodies = bodies.replace(
        position=position, rotation=rotation, velocity=velocity, angular_velocity=angular_velocity
    )
    new_joints = joints.replace(
        acc_impulse=solved.acc_impulse, acc_r_impulse=solved.acc_r_impulse, global_position=solved.anchor
    )
    new_thrusters = state.thrusters.replace(global_position=thruster_positions(state, position, rotation))
    # Cap what is carried to the next step's warm start at the impulse that takes the contact across the whole
    # velocity clamp: more can never be applied, and letting it accumulate (bodies pressed together on the
    # position clamp) grows it geometrically into inf/NaN. Inactive in ordinary contact, where impulses are tiny.
    if num_contacts:
        reach = jnp.sqrt((rows.lever_a**2).sum(-1)) + jnp.sqrt((rows.lever_b**2).sum(-1))
        cap = 2.0 * (params.clip_velocity + params.clip_angular_velocity * reach) * rows.normal_mass
        normal_impulse = jnp.minimum(normal_impulse, cap)
        tangent_impulse = jnp.clip(tangent_impulse, -rows.friction * normal_impulse, rows.friction * normal_impulse)
    cache = ContactCache(normal_impulse=normal_impulse, tangent_impulse=tangent_impulse, active=contacts.touching)
    new_state = state.replace(bodies=new_bodies, joints=new_joints, thrusters=new_thrusters, contacts=cache)

    first = np.concatenate([np.arange(tables.num_rr), np.arange(2 * tables.num_rr, num_contacts)]).astype(int)
    step_contacts = StepContacts(
        touching=contacts.touching[first],
        normal=contacts.normal[first],
        point=contacts.point[first],
        normal_impulse=normal_impulse[first],
    )
    return new_state, step_contacts


def _iterate_phased(
    start: JointSolverState,
    normal_impulse: Array,
    tangent_impulse: Array,
    rows: ContactRows,
    jrows: JointRows,
    joints: Joints,
    params: SimParams,
    sizes: SceneSizes,
    tables: PairTables,
) -> tuple[JointSolverState, Array, Array]:
    """The default schedule: joints in slot order, then contacts phase by phase, with lever arms and effective
    masses fixed per step (cheaper; the joints' position projection does not reach them)."""
    phase_rows = [ContactRows(*(field[phase] for field in rows)) for phase in tables.phases]
    phase_a = [tables.contact_a[phase] for phase in tables.phases]
    phase_b = [tables.contact_b[phase] for phase in tables.phases]

    def iteration(_, carry):
        joint_state, normals, tangents = carry
        for j in range(sizes.num_joints):
            joint_state = solve_joint(joint_state, j, jrows, joints, params)
        v, w = joint_state.velocity, joint_state.angular_velocity
        new_normals, new_tangents = [], []
        for p in range(len(tables.phases)):
            v, w, n_imp, t_imp = solve_phase(v, w, phase_rows[p], phase_a[p], phase_b[p], normals[p], tangents[p])
            new_normals.append(n_imp)
            new_tangents.append(t_imp)
        return joint_state._replace(velocity=v, angular_velocity=w), new_normals, new_tangents

    in_phases = lambda values: [values[phase] for phase in tables.phases]  # noqa: E731
    carry = (start, in_phases(normal_impulse), in_phases(tangent_impulse))
    solved, normals, tangents = jax.lax.fori_loop(0, sizes.num_solver_iterations, iteration, carry)
    if tables.num_contacts:
        slot_order = np.argsort(np.concatenate(tables.phases))
        normal_impulse = jnp.concatenate(normals)[slot_order]
        tangent_impulse = jnp.concatenate(tangents)[slot_order]
    return solved, normal_impulse, tangent_impulse


def _iterate_jax2d(
    start: JointSolverState,
    normal_impulse: Array,
    tangent_impulse: Array,
    contacts: Contacts,
    rows: ContactRows,
    enabled: Array,
    jrows: JointRows,
    joints: Joints,
    params: SimParams,
    sizes: SceneSizes,
    tables: PairTables,
) -> tuple[JointSolverState, Array, Array]:
    """Jax2D's schedule (batched_contacts.py): joints in slot order, then contacts in sorted Jacobi batches of
    16, kind by kind, with lever arms and effective masses taken from the current positions at every visit."""
    constants = ContactConstants(
        point=contacts.point,
        normal=rows.normal,
        tangent=rows.tangent,
        inverse_mass_a=rows.inverse_mass_a,
        inverse_mass_b=rows.inverse_mass_b,
        inverse_inertia_a=rows.inverse_inertia_a,
        inverse_inertia_b=rows.inverse_inertia_b,
        friction=rows.friction,
        target_velocity=rows.target_velocity,
        enabled=enabled,
    )
    batches = batch_slots(tables, contacts.touching) if tables.num_contacts else []

    def iteration(_, carry):
        joint_state, normals, tangents = carry
        for j in range(sizes.num_joints):
            joint_state = solve_joint(joint_state, j, jrows, joints, params)
        v, w, normals, tangents = solve_contacts(
            joint_state.position, joint_state.velocity, joint_state.angular_velocity, normals, tangents,
            batches, constants, tables,
        )
        return joint_state._replace(velocity=v, angular_velocity=w), normals, tangents

    carry = (start, normal_impulse, tangent_impulse)
    return jax.lax.fori_loop(0, sizes.num_solver_iterations, iteration, carry)
