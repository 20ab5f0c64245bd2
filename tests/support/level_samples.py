"""Shared batches of random levels for the level tests (sampled once per process) and numpy views of them."""

from __future__ import annotations

import functools
from types import SimpleNamespace

import jax
import numpy as np

from impulse.engine.levels.generator import sample_random_levels
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_NEUTRAL, ROLE_RED, Level
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes
from impulse.engine.physics.validate import validate_scene

SIZES = {"s": SIZE_S, "m": SIZE_M, "l": SIZE_L}
# Levels sampled per size for the statistics (cheap: sampling is vmapped; validation is the slow part).
STAT_COUNTS = {"s": 4000, "m": 2000, "l": 1000}


@functools.cache
def random_levels(size: str, count: int | None = None, seed: int = 0) -> Level:
    """A batch of random levels on the device (the jitted sampler compiles once per size)."""
    return sample_random_levels(jax.random.key(seed), count or STAT_COUNTS[size], SIZES[size])


def to_host(levels: Level) -> Level:
    return jax.tree.map(np.asarray, levels)


@functools.cache
def host_levels(size: str, count: int | None = None, seed: int = 0) -> Level:
    return to_host(random_levels(size, count, seed))


def take(levels: Level, i: int) -> Level:
    return jax.tree.map(lambda x: x[i], levels)


def problems(levels: Level, count: int) -> list[str]:
    """validate_scene's problems over the first `count` levels of a host batch, each prefixed by its index."""
    found = []
    for i in range(count):
        found += [f"level {i}: {p}" for p in validate_scene(take(levels, i).state)]
    return found


def summary(levels: Level, sizes: SceneSizes) -> SimpleNamespace:
    """Per-level counts (numpy, one entry per level) of a host batch."""
    P, S = sizes.num_polygons, sizes.num_static_polygons
    state = levels.state
    active = state.bodies.active
    shape = active.copy()
    shape[:, :S] = False
    roles = levels.roles
    joints = state.joints
    j_on = joints.active
    fixed_joint = j_on & joints.is_fixed_joint
    motor = j_on & ~joints.is_fixed_joint & joints.motor_on
    thrusters = state.thrusters.active
    return SimpleNamespace(
        polygons=shape[:, :P].sum(1),
        circles=shape[:, P:].sum(1),
        joints=j_on.sum(1),
        fixed_joints=fixed_joint.sum(1),
        motor_on=motor.sum(1),
        thrusters=thrusters.sum(1),
        fixated=(shape & (state.bodies.inverse_mass == 0)).sum(1),
        red=(shape & (roles == ROLE_RED)).sum(1),
        neutral=(shape & (roles == ROLE_NEUTRAL)).sum(1),
        controllable=(motor.sum(1) + thrusters.sum(1)) > 0,
        green_all=(active & (roles == ROLE_GREEN)).sum(1),
        blue_all=(active & (roles == ROLE_BLUE)).sum(1),
        blue_shapes=(shape & (roles == ROLE_BLUE)).sum(1),
        floor=roles[:, 0],
    )
