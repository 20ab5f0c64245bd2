"""The editor's operations on a level: move, rotate, add a circle or a box, set a shape's role, fix or free it,
delete it. The browser sends them (`POST /api/edit`) and gets the edited level back; every change to a level goes
through here, with the engine's own scene-building functions (`engine.physics.building`), so the page computes no
masses and knows no slot layout.

An operation is a JSON object with an "op" field:

- {"op": "move", "body": i, "dx": m, "dy": m}: translate the shape and every shape linked to it through joints
  (a car moves with its wheels; the joints stay intact);
- {"op": "rotate", "body": i, "angle": rad}: turn the shape and its linked shapes about the shape's centre;
- {"op": "add_circle", "x", "y", "radius", "role"?, "fixed"?, "density"?}: a new disc in a free circle slot;
- {"op": "add_polygon", "x", "y", "width", "height", "role"?, "fixed"?, "density"?}: a new 4-vertex box;
- {"op": "set_role", "body": i, "role": "neutral" | "green" | "blue" | "red"};
- {"op": "set_fixed", "body": i, "fixed": bool}: fixed shapes have inverse mass and inertia 0; a freed shape gets
  them back from its geometry and density (Jax2D's convention, which Kinetix's files store);
- {"op": "delete", "body": i}: the shape goes, with the joints and thrusters attached to it.

The arena (the first static polygons) can take a role but not be moved, rotated, freed or deleted. A level is
edited in its own size: when no slot is free the operation is refused, naming the size's limit. After editing,
the collision filter is recomputed (joints may have gone), the contact cache is cleared (it belonged to the old
positions) and the level gets its new content id.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from impulse.engine.levels.level import ROLE_NAMES, Level, with_content_id
from impulse.engine.levels.summary import size_class
from impulse.engine.physics.building import (
    add_circle,
    add_polygon,
    connected_by_joints,
    rectangle_vertices,
    refresh_collision_filter,
)
from impulse.engine.physics.mass import circle_mass_properties, polygon_mass_properties
from impulse.engine.physics.sizes import SceneSizes
from impulse.studio.level_io import LevelInputError

ARENA_METRES = 5.0
MIN_SIZE = 0.05
MAX_SIZE = 2.0
"""Shapes are 5 cm to 2 m across (Kinetix's editor allows at most 2 m: its `max_shape_size`)."""
MASS_CONVENTION = "jax2d"

_refresh = jax.jit(refresh_collision_filter)
# Jitted (one compilation per size, cached on disk by JAX): run eagerly, each costs a compile per primitive.
_add_circle = jax.jit(add_circle, static_argnames=("fixed", "mass_convention"))
_add_polygon = jax.jit(add_polygon, static_argnames=("fixed", "mass_convention"))


def _host(level: Level) -> Level:
    return jax.tree.map(np.array, level)


def _number(op: dict, name: str, low: float | None = None, high: float | None = None, default=None) -> float:
    value = op.get(name, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise LevelInputError(f"{op.get('op')}: {name} must be a finite number, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise LevelInputError(f"{op.get('op')}: {name} must be in [{low}, {high}], got {value}")
    return float(value)


def _role(op: dict) -> int:
    role = op.get("role", "neutral")
    if isinstance(role, str) and role in ROLE_NAMES:
        return ROLE_NAMES.index(role)
    raise LevelInputError(f"{op.get('op')}: role must be one of {', '.join(ROLE_NAMES)}, got {role!r}")


def _flag(op: dict, name: str, default: bool = False) -> bool:
    value = op.get(name, default)
    if not isinstance(value, bool):
        raise LevelInputError(f"{op.get('op')}: {name} must be true or false, got {value!r}")
    return value


def _body(level: Level, sizes: SceneSizes, op: dict, *, arena_ok: bool = False) -> int:
    body = op.get("body")
    if isinstance(body, bool) or not isinstance(body, int) or not 0 <= body < sizes.num_bodies:
        raise LevelInputError(f"{op.get('op')}: body must be a shape's index, 0 to {sizes.num_bodies - 1}, "
                              f"got {body!r}")
    if not level.state.bodies.active[body]:
        raise LevelInputError(f"{op.get('op')}: body {body} is not in the level (its slot is empty)")
    if body < sizes.num_static_polygons and not arena_ok:
        raise LevelInputError(f"{op.get('op')}: body {body} is part of the arena (floor, walls, ceiling), which "
                              "stays where it is")
    return body


def _linked(level: Level, sizes: SceneSizes, body: int) -> np.ndarray:
    """The bodies linked to `body` through joints, itself included ([N] bool)."""
    return np.asarray(connected_by_joints(level.state.joints, sizes.num_bodies))[body]


def _move(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op)
    shift = np.asarray([_number(op, "dx", -10, 10), _number(op, "dy", -10, 10)], np.float32)
    group = _linked(level, sizes, body)
    s = level.state
    joints_moved = np.isin(s.joints.a_index, np.flatnonzero(group)) & s.joints.active
    thrusters_moved = np.isin(s.thrusters.body_index, np.flatnonzero(group)) & s.thrusters.active
    return level.replace(state=s.replace(
        bodies=s.bodies.replace(position=s.bodies.position + group[:, None] * shift),
        joints=s.joints.replace(global_position=s.joints.global_position + joints_moved[:, None] * shift),
        thrusters=s.thrusters.replace(global_position=s.thrusters.global_position + thrusters_moved[:, None] * shift),
    ))


def _rotate(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op)
    angle = _number(op, "angle", -2 * math.pi, 2 * math.pi)
    group = _linked(level, sizes, body)
    s = level.state
    c, n = math.cos(angle), math.sin(angle)
    turn = np.asarray([[c, -n], [n, c]], np.float32)
    pivot = s.bodies.position[body].copy()
    turned = (s.bodies.position - pivot) @ turn.T + pivot
    return level.replace(state=s.replace(bodies=s.bodies.replace(
        position=np.where(group[:, None], turned, s.bodies.position).astype(np.float32),
        rotation=(s.bodies.rotation + group * np.float32(angle)).astype(np.float32),
    )))


def _no_slot(sizes: SceneSizes, kind: str) -> LevelInputError:
    allowed = sizes.num_circles if kind == "circle" else sizes.num_polygons - sizes.num_static_polygons
    return LevelInputError(f"no free {kind} slot: a level of size {size_class(sizes)} holds at most {allowed} "
                           f"{kind}{'s' * (allowed != 1)}{' besides the arena' if kind == 'polygon' else ''}; "
                           "delete one first")


def _add(level: Level, sizes: SceneSizes, op: dict, kind: str) -> Level:
    position = (_number(op, "x", 0, ARENA_METRES), _number(op, "y", 0, ARENA_METRES))
    role = _role(op)
    fixed = _flag(op, "fixed")
    density = _number(op, "density", 0.01, 100, default=1.0)
    options = {"fixed": fixed, "density": density, "mass_convention": MASS_CONVENTION}
    if kind == "circle":
        radius = _number(op, "radius", MIN_SIZE / 2, MAX_SIZE / 2, default=0.25)
        state, index = _add_circle(level.state, position, radius, **options)
    else:
        width = _number(op, "width", MIN_SIZE, MAX_SIZE, default=0.5)
        height = _number(op, "height", MIN_SIZE, MAX_SIZE, default=0.5)
        state, index = _add_polygon(level.state, position, rectangle_vertices(width, height), **options)
    index = int(index)
    if index < 0:
        raise _no_slot(sizes, kind)
    roles, densities = level.roles.copy(), level.densities.copy()
    roles[index], densities[index] = role, density
    return _host(level.replace(state=state)).replace(roles=roles, densities=densities)


def _set_role(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op, arena_ok=True)
    roles = level.roles.copy()
    roles[body] = _role(op)
    return level.replace(roles=roles)


def _mass(level: Level, sizes: SceneSizes, body: int) -> tuple[float, float]:
    """(inverse mass, inverse inertia) of `body` from its geometry and density."""
    s, density = level.state, jnp.float32(level.densities[body])
    if body < sizes.num_polygons:
        _, _, inverse_mass, inverse_inertia = polygon_mass_properties(
            jnp.asarray(s.polygon_vertices[body]), int(s.polygon_n_vertices[body]), density, MASS_CONVENTION)
    else:
        inverse_mass, inverse_inertia = circle_mass_properties(
            jnp.float32(s.circle_radius[body - sizes.num_polygons]), density, MASS_CONVENTION)
    return float(inverse_mass), float(inverse_inertia)


def _set_fixed(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op)
    fixed = _flag(op, "fixed")
    inverse_mass, inverse_inertia = (0.0, 0.0) if fixed else _mass(level, sizes, body)
    b = level.state.bodies
    mass, inertia = b.inverse_mass.copy(), b.inverse_inertia.copy()
    mass[body], inertia[body] = inverse_mass, inverse_inertia
    velocity, spin = b.velocity.copy(), b.angular_velocity.copy()
    if fixed:
        velocity[body], spin[body] = 0.0, 0.0
    return level.replace(state=level.state.replace(bodies=b.replace(
        inverse_mass=mass, inverse_inertia=inertia, velocity=velocity, angular_velocity=spin)))


def _delete(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op)
    s = level.state
    active = s.bodies.active.copy()
    active[body] = False
    joints = s.joints.active & (s.joints.a_index != body) & (s.joints.b_index != body)
    thrusters = s.thrusters.active & (s.thrusters.body_index != body)
    roles = level.roles.copy()
    roles[body] = 0
    return level.replace(roles=roles, state=s.replace(
        bodies=s.bodies.replace(active=active),
        joints=s.joints.replace(active=joints),
        thrusters=s.thrusters.replace(active=thrusters),
    ))


OPERATIONS = {
    "move": _move,
    "rotate": _rotate,
    "add_circle": lambda level, sizes, op: _add(level, sizes, op, "circle"),
    "add_polygon": lambda level, sizes, op: _add(level, sizes, op, "polygon"),
    "set_role": _set_role,
    "set_fixed": _set_fixed,
    "delete": _delete,
}
"""Every operation by its "op" name."""


def apply_edits(level: Level, sizes: SceneSizes, ops: Any) -> Level:
    """`level` (one level of `sizes`) after the operations `ops` (a list of operation objects, applied in order);
    `LevelInputError` naming the operation and the problem for the first one that cannot be applied."""
    if not isinstance(ops, list) or not all(isinstance(op, dict) for op in ops):
        raise LevelInputError("ops must be a list of operation objects, e.g. [{\"op\": \"delete\", \"body\": 4}]")
    edited = _host(level)
    for op in ops:
        apply = OPERATIONS.get(op.get("op"))
        if apply is None:
            raise LevelInputError(f"unknown operation {op.get('op')!r}; known: {', '.join(OPERATIONS)}")
        edited = apply(edited, sizes, op)
    contacts = edited.state.contacts
    cleared = contacts.replace(normal_impulse=np.zeros_like(contacts.normal_impulse),
                               tangent_impulse=np.zeros_like(contacts.tangent_impulse),
                               active=np.zeros_like(contacts.active))
    state = _refresh(edited.state.replace(contacts=cleared))
    return with_content_id(_host(edited.replace(state=state)))
