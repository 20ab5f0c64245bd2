"""A fixed, deterministic engine-action sequence shared by our engine and Jax2D.

Why it exists: the compatibility check (compat_jax2d) runs the same level in both engines and compares
bodies step by step. Zero actions leave motors and thrusters untested, and random actions would need the same
RNG on both sides, so both runners feed this pattern instead. It drives every motor both ways (the sign flips
every 20 steps, staggered by joint) and fires each thruster one third of the time (on for 15 steps, off for
30, staggered by thruster). This file is loaded by path inside the reference virtualenv, so it must depend on
numpy only.
"""

from __future__ import annotations

import numpy as np

MOTOR_PERIOD = 20
THRUSTER_PERIOD = 15


def engine_actions(step: int, num_joints: int, num_thrusters: int) -> np.ndarray:
    """Engine action vector at ``step`` (0-based): ``num_joints`` motor values in {-1, +1}, then
    ``num_thrusters`` thruster values in {0, 1}, as float32 (the layout Jax2D's ``PhysicsEngine.step`` takes).

    motor j = +1 if ((step // 20) + j) is even, else -1;
    thruster k = 1 if ((step // 15) + k) % 3 == 0, else 0.
    """
    joints = np.arange(num_joints)
    thrusters = np.arange(num_thrusters)
    motors = np.where(((step // MOTOR_PERIOD) + joints) % 2 == 0, 1.0, -1.0)
    thrust = np.where(((step // THRUSTER_PERIOD) + thrusters) % 3 == 0, 1.0, 0.0)
    return np.concatenate([motors, thrust]).astype(np.float32)
