"""Impulse's 2D rigid-body engine.

A scene is a structure of fixed-size arrays (a pytree) whose sizes are fixed by a hashable `SceneSizes`, so that
`step` can be jitted once per size (and per `SolverOptions`, how it solves) and vmapped over millions of different
scenes. Behaviour follows Jax2D 1.0.2 as
used by Kinetix (units, parameter names and defaults, contact and joint formulas) so that Kinetix levels keep their
meaning; the solver's schedule and data layout are our own, chosen for throughput. See `docs/engine.md`.
"""

from impulse.engine.physics.building import (
    add_circle,
    add_fixed_joint,
    add_polygon,
    add_rectangle,
    add_revolute_joint,
    add_thruster,
    empty_scene,
    refresh_collision_filter,
)
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes, size_preset
from impulse.engine.physics.state import Bodies, ContactCache, Joints, SimState, Thrusters
from impulse.engine.physics.step import StepContacts, step
from impulse.engine.physics.validate import SceneError, check_scene, validate_scene

__all__ = [
    "SIZE_L",
    "SIZE_M",
    "SIZE_S",
    "Bodies",
    "ContactCache",
    "Joints",
    "SceneError",
    "SceneSizes",
    "SimParams",
    "SimState",
    "SolverOptions",
    "StepContacts",
    "Thrusters",
    "add_circle",
    "add_fixed_joint",
    "add_polygon",
    "add_rectangle",
    "add_revolute_joint",
    "add_thruster",
    "empty_scene",
    "refresh_collision_filter",
    "size_preset",
    "step",
    "validate_scene",
    "check_scene",
]
