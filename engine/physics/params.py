"""Dynamic simulation parameters: traced values, so changing them does not recompile.

Names and defaults are Jax2D 1.0.2's, so that Kinetix level files (which embed these values) keep their meaning.
"""

from __future__ import annotations

from impulse.engine.pytree import pytree_dataclass


@pytree_dataclass
class SimParams:
    dt: float = 1.0 / 60.0
    slop: float = 0.01
    baumgarte_coefficient_joints_v: float = 2.0
    baumgarte_coefficient_joints_p: float = 0.7
    baumgarte_coefficient_fjoint_av: float = 2.0
    baumgarte_coefficient_rjoint_limit_av: float = 5.0
    baumgarte_coefficient_collision: float = 0.2
    joint_stiffness: float = 0.6
    clip_position: float = 15.0
    clip_velocity: float = 100.0
    clip_angular_velocity: float = 50.0
    base_motor_speed: float = 6.0
    base_motor_power: float = 900.0
    base_thruster_power: float = 10.0
    motor_decay_coefficient: float = 0.1
    motor_joint_limit: float = 0.1
    base_friction: float = 0.4
