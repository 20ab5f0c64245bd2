"""Motors and thrusters: one-shot velocity changes applied once per step, before the constraint solve.

Both follow Jax2D: a motor changes the relative spin of its two bodies by at most base_motor_power * power * dt
through the axial mass, shaped by tanh of the speed error and faded out near joint limits; a thruster is an
impulse of base_thruster_power * power * action * dt along its direction.
"""

from __future__ import annotations

import jax.numpy as jnp

from impulse.engine.physics.geometry import cross, nonzero, rotate
from impulse.engine.physics.joint_solver import JointRows
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.slots import one_hot_rows, sum_onto_bodies
from impulse.engine.physics.state import SimState

Array = jnp.ndarray


def apply_motors(
    angular_velocity: Array, state: SimState, rows: JointRows, actions: Array, params: SimParams
) -> Array:
    """Drive each motorised revolute joint towards motor_speed * action * base_motor_speed of relative spin."""
    joints = state.joints
    on = rows.enabled & joints.motor_on & ~joints.is_fixed_joint & (actions != 0)
    iia, iib = rows.inverse_inertia_a, rows.inverse_inertia_b
    axial_mass = 1.0 / nonzero(iia + iib)
    budget = params.base_motor_power * joints.motor_power * params.dt * axial_mass
    w = angular_velocity
    relative_spin = w[joints.b_index] - w[joints.a_index]
    error = relative_spin - joints.motor_speed * actions * params.base_motor_speed
    torque = jnp.tanh(params.motor_decay_coefficient * error)

    # Near a joint limit the motor fades out, unless it drives away from the limit.
    margin = params.motor_joint_limit
    phi = rows.relative_angle
    beyond = phi - jnp.clip(phi, joints.min_rotation + margin, joints.max_rotation - margin)
    fade = jnp.where(
        (beyond == 0) | ~joints.motor_has_joint_limits, 1.0, jnp.maximum(0.0, 1.0 - jnp.abs(beyond) / margin)
    )
    drives_away = jnp.sign(beyond) != jnp.sign(actions)
    budget = budget * jnp.maximum(fade, drives_away.astype(fade.dtype))

    change = budget * torque * on
    return (
        angular_velocity
        + sum_onto_bodies(rows.one_hot_a, change * iia)
        - sum_onto_bodies(rows.one_hot_b, change * iib)
    )


def apply_thrusters(
    velocity: Array, angular_velocity: Array, state: SimState, actions: Array, params: SimParams
) -> tuple[Array, Array]:
    """Push each thruster's body; all thrusters act on the same pre-thrust state and their effects add up."""
    thrusters, bodies = state.thrusters, state.bodies
    num_bodies = bodies.active.shape[0]
    index = thrusters.body_index
    to_body = one_hot_rows(index, num_bodies)
    on = thrusters.active & bodies.active[index]
    magnitude = thrusters.power * params.base_thruster_power * actions * params.dt * on
    body_rotation = bodies.rotation[index]
    angle = thrusters.rotation + body_rotation
    direction = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)
    lever = rotate(body_rotation, thrusters.relative_position)
    impulse = magnitude[:, None] * direction
    dv = bodies.inverse_mass[index][:, None] * impulse
    dw = bodies.inverse_inertia[index] * cross(lever, impulse)
    return (
        velocity + sum_onto_bodies(to_body, dv),
        angular_velocity + sum_onto_bodies(to_body, dw),
    )


def thruster_positions(state: SimState, position: Array, rotation: Array) -> Array:
    thrusters = state.thrusters
    index = thrusters.body_index
    return position[index] + rotate(rotation[index], thrusters.relative_position)
