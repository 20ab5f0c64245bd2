"""Dynamic simulation parameters: traced values, so changing them does not recompile.

Names and defaults are Jax2D 1.0.2's, so that Kinetix level files (which embed these values) keep their meaning.
"""

from __future__ import annotations

from impulse.engine.pytree import pytree_dataclass

CARRIED_IMPULSE_CAP = 64.0
"""How many clamp-crossing impulses an accumulated (carried) impulse may hold: the joint accumulators and the
contact cache are capped at this many times the impulse that takes the pair across the whole velocity clamp
(2 x clip_velocity, 2 x clip_angular_velocity). Jax2D has no cap; ours exists only to stop a constraint that cannot
be met (bodies pressed together on the position clamp) from growing its impulse geometrically into inf/NaN. It is
set far above what a step applies, since velocities are clamped only after the solve: motors and warm starts act
before it, so a weld between two small, light bodies driven by a motor can need more than one crossing (Kinetix's
mjc_half_cheetah needs 1.26 within 5 steps; a cap of one crossing parted it from Jax2D by 17 cm in 120 steps)."""


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
