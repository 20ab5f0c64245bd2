"""The editor's operations on a level: move, rotate, add a circle or a box, set a shape's role, fix or free it,
delete it. The browser sends them (`POST /api/edit`) and gets the edited level back; every change to a level goes
through here, with the engine's own scene-building functions (`engine.physics.building`), so the page computes no
masses and knows no slot layout.

An operation is a JSON object with an "op" field:

- {"op": "move", "body": i, "dx": m, "dy": m}: translate the shape and every shape linked to it through joints
  (a car moves with its wheels; the joints stay intact);
- {"op": "rotate", "body": i, "angle": rad}: turn the shape and its linked shapes about the shape's centre;
- {"op": "add_circle", "x", "y", "radius", "role"?, "fixed"?, "density"?}: a new disc in a free circle slot;
- {"op": "add_polygon", "x", "y", "width", "height", "sides"?, "role"?, "fixed"?, "density"?}: a new box (4 sides,
  the default) or triangle (3: apex up) of that width and height;
- {"op": "set_role", "body": i, "role": "neutral" | "green" | "blue" | "red"};
- {"op": "set_fixed", "body": i, "fixed": bool}: fixed shapes have inverse mass and inertia 0; a freed shape gets
  them back from its geometry and density (Jax2D's convention, which Kinetix's files store);
- {"op": "delete", "body": i}: the shape goes, with the joints and thrusters attached to it;
- {"op": "set_material", "body": i, "density"?, "friction"?, "restitution"?}: a free shape's mass follows its
  new density;
- {"op": "resize", "body": i, "scale": s}: the shape grows or shrinks about its centre (its joint anchors and
  thrusters with it), within the size limits below;
- {"op": "add_joint", "a": i, "b": j, "x", "y", "weld"?, "motor"?, "speed"?, "power"?, "limits"?, "binding"?}: a
  revolute joint (a weld with "weld": true) pinning shapes a and b at the world point (x, y); `a` may be the arena
  (the shape is pinned to the world); "limits": [min, max] radians of relative rotation, from the current angle;
  "binding": which motor action drives it;
- {"op": "set_joint", "joint": k, "motor"?, "speed"?, "power"?, "limits"? (null: none), "binding"?};
- {"op": "add_thruster", "body": i, "x"?, "y"?, "angle"?, "power"?, "binding"?}: a thruster on the shape at the
  world point (x, y) (default: its centre) pushing along the world direction `angle` (radians, default up);
- {"op": "set_thruster", "thruster": k, "power"?, "binding"?, "angle"?}: "angle" turns it to push along that
  world direction (radians);
- {"op": "delete_joint", "joint": k}, {"op": "delete_thruster", "thruster": k}.

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

from impulse.engine.arena import ARENA_METRES
from impulse.engine.levels.level import (
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    ROLE_NAMES,
    Level,
    with_content_id,
)
from impulse.engine.levels.summary import size_class
from impulse.engine.physics.building import (
    add_circle,
    add_fixed_joint,
    add_polygon,
    add_revolute_joint,
    add_thruster,
    connected_by_joints,
    rectangle_vertices,
    refresh_collision_filter,
)
from impulse.engine.physics.mass import circle_mass_properties, polygon_mass_properties
from impulse.engine.physics.sizes import SceneSizes
from impulse.studio.level_io import LevelInputError

MIN_SIZE = 0.05
MAX_SIZE = 2.0
"""Shapes are 5 cm to 2 m across (Kinetix's editor allows at most 2 m: its `max_shape_size`)."""
MASS_CONVENTION = "jax2d"

_refresh = jax.jit(refresh_collision_filter)
# Jitted (one compilation per size, cached on disk by JAX): run eagerly, each costs a compile per primitive.
_add_circle = jax.jit(add_circle, static_argnames=("fixed", "mass_convention"))
_add_polygon = jax.jit(add_polygon, static_argnames=("fixed", "mass_convention"))
_add_revolute = jax.jit(add_revolute_joint, static_argnames=("motor_on", "has_joint_limits"))
_add_weld = jax.jit(add_fixed_joint)
_put_thruster = jax.jit(add_thruster)
MAX_MOTOR_SPEED = 10.0
MAX_POWER = 10.0
"""Motor speed and motor and thruster power are multiples of the engine's base values (Kinetix's editor: 0 to 3)."""


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


def _index(op: dict, name: str, count: int, what: str) -> int:
    value = op.get(name)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < count:
        raise LevelInputError(f"{op.get('op')}: {name} must be {what}'s index, 0 to {count - 1}, got {value!r}")
    return value


def _body(level: Level, sizes: SceneSizes, op: dict, *, arena_ok: bool = False, field: str = "body") -> int:
    body = _index(op, field, sizes.num_bodies, "a shape")
    if not level.state.bodies.active[body]:
        raise LevelInputError(f"{op.get('op')}: {field} {body} is not in the level (its slot is empty)")
    if body < sizes.num_static_polygons and not arena_ok:
        raise LevelInputError(f"{op.get('op')}: {field} {body} is part of the arena (floor, walls, ceiling), which "
                              "stays where it is")
    return body


def _slot(table: Any, op: dict, name: str, what: str) -> int:
    slot = _index(op, name, table.active.shape[0], what)
    if not table.active[slot]:
        raise LevelInputError(f"{op.get('op')}: {name} {slot} is not in the level (its slot is empty)")
    return slot


def _binding(op: dict, count: int) -> int | None:
    if "binding" not in op:
        return None
    return _index(op, "binding", count, "an action")


def _limits(op: dict) -> tuple[float, float] | None:
    limits = op.get("limits")
    if limits is None:
        return None
    if not isinstance(limits, list) or len(limits) != 2:
        raise LevelInputError(f"{op.get('op')}: limits must be [min, max] in radians or null, got {limits!r}")
    low, high = (_number({"op": op.get("op"), "limit": x}, "limit", -2 * math.pi, 2 * math.pi) for x in limits)
    if low >= high:
        raise LevelInputError(f"{op.get('op')}: limits must have min < max, got {limits!r}")
    return low, high


def _local(level: Level, body: int, point: np.ndarray) -> np.ndarray:
    """A world point in `body`'s frame (relative to its centre of mass)."""
    angle = float(level.state.bodies.rotation[body])
    c, n = math.cos(-angle), math.sin(-angle)
    offset = point - level.state.bodies.position[body]
    return np.asarray([c * offset[0] - n * offset[1], n * offset[0] + c * offset[1]], np.float32)


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
        sides = op.get("sides", 4)
        if sides not in (3, 4) or isinstance(sides, bool):
            raise LevelInputError(f"add_polygon: sides must be 3 or 4, got {sides!r}")
        vertices = rectangle_vertices(width, height) if sides == 4 else np.asarray(
            [[-width / 2, -height / 2], [0.0, height / 2], [width / 2, -height / 2]], np.float32)  # clockwise
        state, index = _add_polygon(level.state, position, vertices, **options)
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


def _set_material(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op, arena_ok=True)
    b = level.state.bodies
    friction, restitution = b.friction.copy(), b.restitution.copy()
    if "friction" in op:
        friction[body] = _number(op, "friction", 0, 5)
    if "restitution" in op:
        restitution[body] = _number(op, "restitution", 0, 1)
    level = level.replace(state=level.state.replace(bodies=b.replace(friction=friction, restitution=restitution)))
    if "density" not in op:
        return level
    if body < sizes.num_static_polygons:
        raise LevelInputError(f"set_material: body {body} is part of the arena, which has no mass")
    densities = level.densities.copy()
    densities[body] = _number(op, "density", 0.01, 100)
    level = level.replace(densities=densities)
    return _with_mass(level, sizes, body)


def _with_mass(level: Level, sizes: SceneSizes, body: int) -> Level:
    """`level` with `body`'s inverse mass and inertia from its geometry and density (none while it is fixed)."""
    b = level.state.bodies
    if b.inverse_mass[body] == 0:
        return level
    mass, inertia = b.inverse_mass.copy(), b.inverse_inertia.copy()
    mass[body], inertia[body] = _mass(level, sizes, body)
    return level.replace(state=level.state.replace(bodies=b.replace(inverse_mass=mass, inverse_inertia=inertia)))


def _resize(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op)
    scale = _number(op, "scale", 0.1, 10)
    s = level.state
    if body < sizes.num_polygons:
        vertices = s.polygon_vertices.copy()
        n = int(s.polygon_n_vertices[body])
        extent = np.ptp(vertices[body, :n], axis=0).max() * scale
        vertices[body] *= np.float32(scale)
        state = s.replace(polygon_vertices=vertices)
    else:
        radius = s.circle_radius.copy()
        extent = 2 * radius[body - sizes.num_polygons] * scale
        radius[body - sizes.num_polygons] *= np.float32(scale)
        state = s.replace(circle_radius=radius)
    if not MIN_SIZE <= extent <= MAX_SIZE:
        raise LevelInputError(f"resize: the shape would be {extent:.2f} m across; shapes are {MIN_SIZE} to "
                              f"{MAX_SIZE} m")
    j, t = state.joints, state.thrusters
    on_a, on_b = (j.a_index == body) & j.active, (j.b_index == body) & j.active
    on_body = (t.body_index == body) & t.active
    state = state.replace(
        joints=j.replace(a_relative_pos=np.where(on_a[:, None], j.a_relative_pos * scale, j.a_relative_pos),
                         b_relative_pos=np.where(on_b[:, None], j.b_relative_pos * scale, j.b_relative_pos)),
        thrusters=t.replace(relative_position=np.where(on_body[:, None], t.relative_position * scale,
                                                       t.relative_position)))
    return _with_mass(_host(level.replace(state=state)), sizes, body)


def _motor_fields(op: dict, motor_on: bool, speed: float, power: float,
                  limits: tuple[float, float] | None) -> tuple[bool, float, float, tuple[float, float] | None]:
    """The motor settings `op` asks for, each defaulting to the current one."""
    motor_on = _flag(op, "motor", motor_on)
    speed = _number(op, "speed", -MAX_MOTOR_SPEED, MAX_MOTOR_SPEED, default=speed)
    power = _number(op, "power", 0, MAX_POWER, default=power)
    return motor_on, speed, power, (_limits(op) if "limits" in op else limits)


def _add_joint(level: Level, sizes: SceneSizes, op: dict) -> Level:
    a = _body(level, sizes, op, arena_ok=True, field="a")
    b = _body(level, sizes, op, field="b")
    if a == b:
        raise LevelInputError("add_joint: a and b must be two different shapes")
    anchor = np.asarray([_number(op, "x", 0, ARENA_METRES), _number(op, "y", 0, ARENA_METRES)], np.float32)
    if not (~level.state.joints.active).any():
        raise LevelInputError(f"no free joint slot: a level of size {size_class(sizes)} holds at most "
                              f"{sizes.num_joints} joints; delete one first")
    a_local, b_local = _local(level, a, anchor), _local(level, b, anchor)
    if _flag(op, "weld"):
        state, slot = _add_weld(level.state, a, b, a_local, b_local)
    else:
        motor_on, speed, power, limits = _motor_fields(op, False, 1.0, 1.0, None)
        state, slot = _add_revolute(level.state, a, b, a_local, b_local, motor_on=motor_on, motor_speed=speed,
                                    motor_power=power, has_joint_limits=limits is not None,
                                    min_rotation=limits[0] if limits else -math.pi,
                                    max_rotation=limits[1] if limits else math.pi)
    level = _host(level.replace(state=state))
    slot = int(slot)
    bindings = level.motor_bindings.copy()
    bindings[slot] = _binding(op, NUM_MOTOR_BINDINGS) or 0
    joints = level.state.joints
    world = joints.global_position.copy()
    world[slot] = anchor
    return level.replace(motor_bindings=bindings, state=level.state.replace(
        joints=joints.replace(global_position=world)))


def _set_joint(level: Level, sizes: SceneSizes, op: dict) -> Level:
    j = level.state.joints
    k = _slot(j, op, "joint", "a joint")
    if j.is_fixed_joint[k]:
        raise LevelInputError(f"set_joint: joint {k} is a weld, which has no motor or limits")
    limits = (float(j.min_rotation[k]), float(j.max_rotation[k])) if j.motor_has_joint_limits[k] else None
    motor_on, speed, power, limits = _motor_fields(op, bool(j.motor_on[k]), float(j.motor_speed[k]),
                                                   float(j.motor_power[k]), limits)
    fields = {name: getattr(j, name).copy() for name in ("motor_on", "motor_speed", "motor_power",
                                                         "motor_has_joint_limits", "min_rotation", "max_rotation")}
    fields["motor_on"][k], fields["motor_speed"][k], fields["motor_power"][k] = motor_on, speed, power
    fields["motor_has_joint_limits"][k] = limits is not None
    if limits is not None:
        fields["min_rotation"][k], fields["max_rotation"][k] = limits
    bindings = level.motor_bindings.copy()
    binding = _binding(op, NUM_MOTOR_BINDINGS)
    if binding is not None:
        bindings[k] = binding
    return level.replace(motor_bindings=bindings, state=level.state.replace(joints=j.replace(**fields)))


def _add_thruster(level: Level, sizes: SceneSizes, op: dict) -> Level:
    body = _body(level, sizes, op)
    centre = level.state.bodies.position[body]
    point = np.asarray([_number(op, "x", 0, ARENA_METRES, default=float(centre[0])),
                        _number(op, "y", 0, ARENA_METRES, default=float(centre[1]))], np.float32)
    angle = _number(op, "angle", -2 * math.pi, 2 * math.pi, default=math.pi / 2)
    power = _number(op, "power", 0, MAX_POWER, default=1.0)
    if not (~level.state.thrusters.active).any():
        raise LevelInputError(f"no free thruster slot: a level of size {size_class(sizes)} holds at most "
                              f"{sizes.num_thrusters} thruster{'s' * (sizes.num_thrusters != 1)}; delete one first")
    rotation = angle - float(level.state.bodies.rotation[body])
    state, slot = _put_thruster(level.state, body, _local(level, body, point), rotation, power)
    level = _host(level.replace(state=state))
    bindings = level.thruster_bindings.copy()
    bindings[int(slot)] = _binding(op, NUM_THRUSTER_BINDINGS) or 0
    return level.replace(thruster_bindings=bindings)


def _set_thruster(level: Level, sizes: SceneSizes, op: dict) -> Level:
    t = level.state.thrusters
    k = _slot(t, op, "thruster", "a thruster")
    power = t.power.copy()
    power[k] = _number(op, "power", 0, MAX_POWER, default=float(power[k]))
    rotation = t.rotation.copy()
    if op.get("angle") is not None:
        body = int(t.body_index[k])
        angle = _number(op, "angle", -2 * math.pi, 2 * math.pi, default=0.0)
        rotation[k] = np.float32(angle - float(level.state.bodies.rotation[body]))
    bindings = level.thruster_bindings.copy()
    binding = _binding(op, NUM_THRUSTER_BINDINGS)
    if binding is not None:
        bindings[k] = binding
    return level.replace(thruster_bindings=bindings,
                         state=level.state.replace(thrusters=t.replace(power=power, rotation=rotation)))


def _delete_joint(level: Level, sizes: SceneSizes, op: dict) -> Level:
    j = level.state.joints
    active = j.active.copy()
    active[_slot(j, op, "joint", "a joint")] = False
    return level.replace(state=level.state.replace(joints=j.replace(active=active)))


def _delete_thruster(level: Level, sizes: SceneSizes, op: dict) -> Level:
    t = level.state.thrusters
    active = t.active.copy()
    active[_slot(t, op, "thruster", "a thruster")] = False
    return level.replace(state=level.state.replace(thrusters=t.replace(active=active)))


OPERATIONS = {
    "move": _move,
    "rotate": _rotate,
    "add_circle": lambda level, sizes, op: _add(level, sizes, op, "circle"),
    "add_polygon": lambda level, sizes, op: _add(level, sizes, op, "polygon"),
    "set_role": _set_role,
    "set_fixed": _set_fixed,
    "delete": _delete,
    "set_material": _set_material,
    "resize": _resize,
    "add_joint": _add_joint,
    "set_joint": _set_joint,
    "add_thruster": _add_thruster,
    "set_thruster": _set_thruster,
    "delete_joint": _delete_joint,
    "delete_thruster": _delete_thruster,
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
