"""Joints: Jax2D's revolute/fixed joint formulation (velocity impulse along the relative velocity, direct
position projection, angular lock or limits), solved one joint at a time in slot order.

Joint body indices are data (each level wires its own), so a joint reads and writes bodies through one-hot
weights: a multiply-sum over the bodies, which fuses on every backend where a gather or scatter would not.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from impulse.engine.physics.geometry import cross, nonzero, rotate
from impulse.engine.physics.params import CARRIED_IMPULSE_CAP, SimParams
from impulse.engine.physics.slots import one_hot_rows, read_body, spread_to_bodies, sum_onto_bodies
from impulse.engine.physics.state import Joints, SimState

Array = jnp.ndarray


class JointRows(NamedTuple):
    """Per-joint constants of one step."""

    one_hot_a: Array  # [J, N]
    one_hot_b: Array  # [J, N]
    lever_a: Array  # [J, 2] anchor offset from a's centre of mass, world frame
    lever_b: Array
    inverse_mass_a: Array  # [J]
    inverse_mass_b: Array
    inverse_inertia_a: Array
    inverse_inertia_b: Array
    relative_angle: Array  # [J] theta_b - theta_a - reference, unwrapped
    enabled: Array  # [J] bool


def joint_rows(state: SimState) -> JointRows:
    joints, bodies = state.joints, state.bodies
    num_bodies = bodies.active.shape[0]
    one_hot_a = one_hot_rows(joints.a_index, num_bodies)
    one_hot_b = one_hot_rows(joints.b_index, num_bodies)
    a, b = joints.a_index, joints.b_index
    ima, imb = bodies.inverse_mass[a], bodies.inverse_mass[b]
    enabled = joints.active & bodies.active[a] & bodies.active[b] & ~((ima == 0) & (imb == 0))
    on = enabled.astype(jnp.float32)
    return JointRows(
        one_hot_a=one_hot_a,
        one_hot_b=one_hot_b,
        lever_a=rotate(bodies.rotation[a], joints.a_relative_pos),
        lever_b=rotate(bodies.rotation[b], joints.b_relative_pos),
        inverse_mass_a=ima * on,
        inverse_mass_b=imb * on,
        inverse_inertia_a=bodies.inverse_inertia[a] * on,
        inverse_inertia_b=bodies.inverse_inertia[b] * on,
        relative_angle=bodies.rotation[b] - bodies.rotation[a] - joints.rotation,
        enabled=enabled,
    )


def warm_start_joints(
    velocity: Array, angular_velocity: Array, rows: JointRows, joints: Joints
) -> tuple[Array, Array]:
    """Re-apply last step's joint impulses (all joints at once: they do not depend on velocity)."""
    impulse = joints.acc_impulse * rows.enabled[:, None]
    angular = joints.acc_r_impulse * (rows.enabled & joints.is_fixed_joint)
    velocity = velocity + sum_onto_bodies(rows.one_hot_a, rows.inverse_mass_a[:, None] * impulse)
    velocity = velocity - sum_onto_bodies(rows.one_hot_b, rows.inverse_mass_b[:, None] * impulse)
    dw_a = rows.inverse_inertia_a * (cross(rows.lever_a, impulse) + angular)
    dw_b = rows.inverse_inertia_b * (cross(rows.lever_b, impulse) + angular)
    angular_velocity = angular_velocity + sum_onto_bodies(rows.one_hot_a, dw_a)
    angular_velocity = angular_velocity - sum_onto_bodies(rows.one_hot_b, dw_b)
    return velocity, angular_velocity


class JointSolverState(NamedTuple):
    """What the solver iterations change: body state (joints move positions too) and joint accumulators."""

    position: Array  # [N, 2]
    velocity: Array  # [N, 2]
    angular_velocity: Array  # [N]
    acc_impulse: Array  # [J, 2]
    acc_r_impulse: Array  # [J]
    anchor: Array  # [J, 2] world joint point


def solve_joint(
    s: JointSolverState, j: int, rows: JointRows, joints: Joints, params: SimParams
) -> JointSolverState:
    """One Gauss-Seidel visit of joint j. Disabled joints have zeroed inverse masses in `rows`, so they move
    nothing, and store zeros."""
    oa, ob = rows.one_hot_a[j], rows.one_hot_b[j]
    xa, xb = read_body(s.position, oa), read_body(s.position, ob)
    va, vb = read_body(s.velocity, oa), read_body(s.velocity, ob)
    wa, wb = read_body(s.angular_velocity, oa), read_body(s.angular_velocity, ob)
    on = rows.enabled[j]
    ima, imb = rows.inverse_mass_a[j], rows.inverse_mass_b[j]
    iia, iib = rows.inverse_inertia_a[j], rows.inverse_inertia_b[j]
    ra, rb = rows.lever_a[j], rows.lever_b[j]

    # Linear part: an impulse along the relative velocity at the mass-weighted joint point, plus a direct
    # position projection that pulls the two anchors together.
    anchor_a, anchor_b = xa + ra, xb + rb
    mass_a, mass_b = 1.0 / nonzero(ima), 1.0 / nonzero(imb)
    joint_point = (anchor_a * mass_a + anchor_b * mass_b) / (mass_a + mass_b)
    joint_point = jnp.where(ima == 0, anchor_a, jnp.where(imb == 0, anchor_b, joint_point))
    arm_a, arm_b = joint_point - xa, joint_point - xb
    relative = (vb + wb * jnp.stack([-arm_b[1], arm_b[0]])) - (va + wa * jnp.stack([-arm_a[1], arm_a[0]]))
    speed = jnp.sqrt(relative[0] ** 2 + relative[1] ** 2)
    direction = relative / nonzero(speed)
    denominator = nonzero(ima + imb) + cross(ra, direction) ** 2 * iia + cross(rb, direction) ** 2 * iib
    error = anchor_b - anchor_a
    impulse = (
        params.joint_stiffness * (relative + params.baumgarte_coefficient_joints_v * error) / nonzero(denominator)
    ) * on
    dva, dvb = ima * impulse, -imb * impulse
    new_wa, new_wb = wa + iia * cross(ra, impulse), wb - iib * cross(rb, impulse)
    share = params.baumgarte_coefficient_joints_p * error / nonzero(ima + imb)
    dxa, dxb = share * ima, -share * imb

    # Angular part, on velocities that include the linear impulse's spin.
    raw = new_wb - new_wa
    phi = rows.relative_angle[j]
    fixed = joints.is_fixed_joint[j]
    limit_error = phi - jnp.clip(phi, joints.min_rotation[j], joints.max_rotation[j])
    limit_bias = params.baumgarte_coefficient_rjoint_limit_av * limit_error
    limited = (
        ~fixed
        & joints.motor_has_joint_limits[j]
        & (limit_error != 0)
        & (jnp.sign(raw) == jnp.sign(limit_bias))
    )
    target = jnp.where(fixed, raw + params.baumgarte_coefficient_fjoint_av * phi, raw + limit_bias)
    angular_impulse = jnp.where(fixed | limited, target / nonzero(iia + iib), 0.0) * on
    new_wa = new_wa + angular_impulse * iia
    new_wb = new_wb - angular_impulse * iib

    # The accumulators feed next step's warm start; capped (CARRIED_IMPULSE_CAP clamp crossings) only so that a
    # constraint that cannot be met (bodies pinned by the position clamp) does not grow them into inf/NaN.
    acc = s.acc_impulse[j] + impulse
    acc_cap = CARRIED_IMPULSE_CAP * 2.0 * params.clip_velocity / nonzero(ima + imb)
    acc_norm = jnp.sqrt(acc[0] ** 2 + acc[1] ** 2)
    acc = acc * jnp.minimum(1.0, acc_cap / nonzero(acc_norm))
    r_cap = CARRIED_IMPULSE_CAP * 2.0 * params.clip_angular_velocity / nonzero(iia + iib)
    acc_r = jnp.clip(s.acc_r_impulse[j] + angular_impulse, -r_cap, r_cap)

    return JointSolverState(
        position=s.position + spread_to_bodies(oa, dxa) + spread_to_bodies(ob, dxb),
        velocity=s.velocity + spread_to_bodies(oa, dva) + spread_to_bodies(ob, dvb),
        angular_velocity=(
            s.angular_velocity + spread_to_bodies(oa, new_wa - wa) + spread_to_bodies(ob, new_wb - wb)
        ),
        acc_impulse=s.acc_impulse.at[j].set(jnp.where(on, acc, 0.0)),
        acc_r_impulse=s.acc_r_impulse.at[j].set(jnp.where(on & fixed, acc_r, 0.0)),
        anchor=s.anchor.at[j].set(jnp.where(on, joint_point, 0.0)),
    )
