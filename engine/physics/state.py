"""The scene as a structure of arrays.

Polygons and circles share one body array (polygons first, then circles), so a joint's or thruster's body index is
simply an index into it; this is Jax2D's "global index". Shape geometry that only one kind has (vertices, radius)
lives in its own arrays. All leaves have a leading slot axis; a batch of scenes adds one more axis in front.
"""

from __future__ import annotations

import jax

from impulse.engine.pytree import pytree_dataclass

Array = jax.Array


@pytree_dataclass
class Bodies:
    """N = P + C rigid bodies. `inverse_mass == 0` means fixed (infinite mass); `active` marks used slots."""

    position: Array  # [N, 2] centre of mass, world frame
    rotation: Array  # [N] radians, never wrapped
    velocity: Array  # [N, 2]
    angular_velocity: Array  # [N]
    inverse_mass: Array  # [N]
    inverse_inertia: Array  # [N]
    friction: Array  # [N] per-shape coefficient, scaled by SimParams.base_friction
    restitution: Array  # [N] combined by min
    collision_mode: Array  # [N] int32: 0 touches only mode 2, 1 touches 1 and 2, 2 touches everything
    active: Array  # [N] bool


@pytree_dataclass
class Joints:
    """J revolute or fixed joints between two bodies, with optional motors and angle limits."""

    a_index: Array  # [J] int32 body index
    b_index: Array  # [J] int32 body index
    a_relative_pos: Array  # [J, 2] anchor in a's local frame, relative to its centre of mass
    b_relative_pos: Array  # [J, 2]
    rotation: Array  # [J] reference relative angle (theta_b - theta_a) held by fixed joints, origin of limits
    active: Array  # [J] bool
    is_fixed_joint: Array  # [J] bool
    motor_on: Array  # [J] bool
    motor_speed: Array  # [J] multiplier of base_motor_speed
    motor_power: Array  # [J] multiplier of base_motor_power
    motor_has_joint_limits: Array  # [J] bool
    min_rotation: Array  # [J]
    max_rotation: Array  # [J]
    acc_impulse: Array  # [J, 2] linear impulse of the last step (warm start)
    acc_r_impulse: Array  # [J] angular impulse of the last step (fixed joints)
    global_position: Array  # [J, 2] world anchor, written by the solver


@pytree_dataclass
class Thrusters:
    """T thrusters, each pushing one body along a direction fixed in that body's frame."""

    body_index: Array  # [T] int32
    relative_position: Array  # [T, 2] local offset from the body's centre of mass
    rotation: Array  # [T] thrust direction relative to the body
    power: Array  # [T] multiplier of base_thruster_power
    active: Array  # [T] bool
    global_position: Array  # [T, 2] world position, updated at the end of each step


@pytree_dataclass
class ContactCache:
    """Accumulated contact impulses of the last step, one per contact slot (see `pairs.PairTables`)."""

    normal_impulse: Array  # [K]
    tangent_impulse: Array  # [K]
    active: Array  # [K] bool: the slot was touching last step


@pytree_dataclass
class SimState:
    bodies: Bodies
    polygon_vertices: Array  # [P, V, 2] local frame, clockwise, relative to the centre of mass
    polygon_n_vertices: Array  # [P] int32 (3..V)
    circle_radius: Array  # [C]
    joints: Joints
    thrusters: Thrusters
    contacts: ContactCache
    pair_collides: Array  # [num_pairs] bool: false for pairs connected through joints (computed at build time)
    gravity: Array  # [2]
