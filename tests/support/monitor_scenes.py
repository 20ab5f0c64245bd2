"""A small known scene shared by the level-file and monitoring tests: one of each kind of part, roles set."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.levels.level import level_from_scene
from impulse.engine.physics.building import add_circle, add_rectangle, add_revolute_joint, add_thruster, empty_scene
from impulse.engine.physics.sizes import SIZE_S

GREEN_AT = (1.5, 2.5)  # centre of the green box
BLUE_AT = (3.8, 1.0)  # centre of the (fixed) blue circle


def small_level():
    """The level below, built by one compiled call (cheaper than running the builders eagerly)."""
    return jax.tree.map(np.asarray, _compiled()())


@functools.cache
def _compiled():
    return jax.jit(_small_level)


def _small_level():
    """S-sized: a green box with a thruster, a blue fixed ball, a red ball hinged to the box by a motor."""
    s = empty_scene(SIZE_S)
    s, box = add_rectangle(s, GREEN_AT, 0.8, 0.6)
    s, blue = add_circle(s, BLUE_AT, 0.3, fixed=True)
    s, red = add_circle(s, (2.3, 2.5), 0.2)
    s, _ = add_revolute_joint(s, box, red, (0.4, 0.0), (-0.4, 0.0), motor_on=True)
    s, _ = add_thruster(s, box, (-0.3, 0.0), rotation=0.0, power=0.5)
    roles = jnp.zeros(SIZE_S.num_bodies, jnp.int32).at[jnp.stack([box, blue, red])].set(jnp.array([1, 2, 3]))
    return level_from_scene(s, roles, motor_bindings=jnp.array([1], jnp.int32))


