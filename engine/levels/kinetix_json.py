"""Import of Kinetix's JSON level files into the engine's scene layout.

A Kinetix file stores Jax2D's state as separate polygon and circle lists (array-of-structs, every slot included),
arrays encoded as objects keyed "0", "1", ...; see the Kinetix digest's level-format section. We keep the stored
inverse masses and inertias (they encode Jax2D's mass conventions), recompute the joint collision filter, and
start with an empty contact cache, as Kinetix's own loader effectively does.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from engine.levels.level import Level
from engine.physics.params import SimParams
from engine.physics.scene import empty_scene, refresh_collision_filter
from engine.physics.sizes import SceneSizes
from engine.physics.state import SimState


class LevelFileError(ValueError):
    """A level file is malformed or does not fit; the message names the file, field and problem."""


@dataclass(frozen=True)
class KinetixLevel:
    """A loaded level: the physics scene plus the task data Kinetix keeps beside it."""

    state: SimState
    sizes: SceneSizes
    params: SimParams
    polygon_roles: np.ndarray  # [P] 0 neutral, 1 green, 2 blue, 3 red
    circle_roles: np.ndarray  # [C]
    polygon_densities: np.ndarray
    circle_densities: np.ndarray
    motor_bindings: np.ndarray  # [J]
    thruster_bindings: np.ndarray  # [T]
    frame_skip: int

    @property
    def level(self) -> Level:
        """The scene and its task data as one pytree, roles and densities in body order."""
        return Level(
            state=self.state,
            roles=jnp.asarray(np.concatenate([self.polygon_roles, self.circle_roles]), jnp.int32),
            densities=jnp.asarray(np.concatenate([self.polygon_densities, self.circle_densities]), jnp.float32),
            motor_bindings=jnp.asarray(self.motor_bindings, jnp.int32),
            thruster_bindings=jnp.asarray(self.thruster_bindings, jnp.int32),
        )


def decode_arrays(value: Any) -> Any:
    """Turn Kinetix's {"0": a, "1": b} array encoding back into (nested) lists."""
    if isinstance(value, dict):
        if "0" in value and all(k.isdigit() for k in value):
            return [decode_arrays(value[str(i)]) for i in range(len(value))]
        return {k: decode_arrays(v) for k, v in value.items()}
    if isinstance(value, list):
        return [decode_arrays(v) for v in value]
    return value


_BODY_FIELDS = {
    "position": np.float32,
    "rotation": np.float32,
    "velocity": np.float32,
    "angular_velocity": np.float32,
    "inverse_mass": np.float32,
    "inverse_inertia": np.float32,
    "friction": np.float32,
    "restitution": np.float32,
    "collision_mode": np.int32,
    "active": bool,
}
_JOINT_FIELDS = {
    "a_index": np.int32,
    "b_index": np.int32,
    "a_relative_pos": np.float32,
    "b_relative_pos": np.float32,
    "rotation": np.float32,
    "active": bool,
    "is_fixed_joint": bool,
    "motor_on": bool,
    "motor_speed": np.float32,
    "motor_power": np.float32,
    "motor_has_joint_limits": bool,
    "min_rotation": np.float32,
    "max_rotation": np.float32,
    "acc_impulse": np.float32,
    "acc_r_impulse": np.float32,
    "global_position": np.float32,
}
_THRUSTER_FIELDS = {
    "object_index": np.int32,
    "relative_position": np.float32,
    "rotation": np.float32,
    "power": np.float32,
    "active": bool,
    "global_position": np.float32,
}


def _column(entries: list[dict], field: str, dtype, where: str) -> np.ndarray:
    try:
        values = [entry[field] for entry in entries]
    except KeyError:
        raise LevelFileError(f"{where}: missing field {field!r}") from None
    except TypeError:
        raise LevelFileError(f"{where}: entries must be objects") from None
    try:
        arr = np.asarray(values, dtype=dtype)
    except (TypeError, ValueError):
        raise LevelFileError(f"{where}.{field}: expected numbers of one shape") from None
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise LevelFileError(f"{where}.{field}: NaN or infinite value")
    return arr


def _entity_list(env_state: dict, key: str, where: str) -> list[dict]:
    value = env_state.get(key)
    if not isinstance(value, list):
        raise LevelFileError(f"{where}: env_state.{key} must be a list of slot objects")
    return value


def load_kinetix_level(path: str | Path, sizes: SceneSizes | None = None) -> KinetixLevel:
    """Load a Kinetix JSON level; with `sizes` given, pad it into those (larger or equal) slot counts."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise LevelFileError(f"{path}: cannot read level file: {err}") from err
    if not isinstance(raw, dict) or "env_state" not in raw:
        raise LevelFileError(f"{path}: not a Kinetix level (no env_state object)")
    data = decode_arrays(raw)
    env_state = data["env_state"]
    where = str(path)
    polygons = _entity_list(env_state, "polygon", where)
    circles = _entity_list(env_state, "circle", where)
    joints = _entity_list(env_state, "joint", where)
    thrusters = _entity_list(env_state, "thruster", where)
    static = data.get("static_env_params", {})
    file_sizes = SceneSizes(
        num_polygons=len(polygons),
        num_circles=len(circles),
        num_joints=len(joints),
        num_thrusters=len(thrusters),
        max_polygon_vertices=int(static.get("max_polygon_vertices", 4)),
        num_static_polygons=int(static.get("num_static_fixated_polys", 4)),
        num_solver_iterations=int(static.get("num_solver_iterations", 10)),
        warm_starting=bool(static.get("do_warm_starting", True)),
    )
    target = sizes or file_sizes
    if not file_sizes.fits_in(target):
        raise LevelFileError(
            f"{path}: level needs {file_sizes.num_polygons} polygons, {file_sizes.num_circles} circles, "
            f"{file_sizes.num_joints} joints, {file_sizes.num_thrusters} thrusters but the size allows "
            f"{target.num_polygons}, {target.num_circles}, {target.num_joints}, {target.num_thrusters}"
        )
    P, C, Pt = file_sizes.num_polygons, file_sizes.num_circles, target.num_polygons

    def shift(index: np.ndarray) -> np.ndarray:
        # Circles move up when polygon slots are added in front of them.
        return np.where(index >= P, index + (Pt - P), index).astype(np.int32)

    state = empty_scene(target)
    b = state.bodies
    body_updates = {}
    for field, dtype in _BODY_FIELDS.items():
        poly = _column(polygons, field, dtype, f"{where}: polygon") if P else None
        circ = _column(circles, field, dtype, f"{where}: circle") if C else None
        arr = np.array(getattr(b, field))
        if poly is not None:
            arr[:P] = poly
        if circ is not None:
            arr[Pt : Pt + C] = circ
        body_updates[field] = jnp.asarray(arr)
    vertices = np.array(state.polygon_vertices)
    n_vertices = np.array(state.polygon_n_vertices)
    if P:
        verts = _column(polygons, "vertices", np.float32, f"{where}: polygon")
        if verts.ndim != 3 or verts.shape[2] != 2 or verts.shape[1] > target.max_polygon_vertices:
            raise LevelFileError(f"{where}: polygon.vertices must be [slots, <= {target.max_polygon_vertices}, 2]")
        vertices[:P, : verts.shape[1]] = verts
        n_vertices[:P] = _column(polygons, "n_vertices", np.int32, f"{where}: polygon")
    radius = np.array(state.circle_radius)
    if C:
        radius[:C] = _column(circles, "radius", np.float32, f"{where}: circle")

    joint_updates = {}
    for field, dtype in _JOINT_FIELDS.items():
        arr = np.array(getattr(state.joints, field))
        if joints:
            col = _column(joints, field, dtype, f"{where}: joint")
            arr[: len(joints)] = shift(col) if field in ("a_index", "b_index") else col
        joint_updates[field] = jnp.asarray(arr)
    thruster_updates = {}
    for field, dtype in _THRUSTER_FIELDS.items():
        ours = "body_index" if field == "object_index" else field
        arr = np.array(getattr(state.thrusters, ours))
        if thrusters:
            col = _column(thrusters, field, dtype, f"{where}: thruster")
            arr[: len(thrusters)] = shift(col) if field == "object_index" else col
        thruster_updates[ours] = jnp.asarray(arr)

    gravity = np.asarray(env_state.get("gravity", [0.0, -9.81]), np.float32)
    state = state.replace(
        bodies=b.replace(**body_updates),
        polygon_vertices=jnp.asarray(vertices),
        polygon_n_vertices=jnp.asarray(n_vertices),
        circle_radius=jnp.asarray(radius),
        joints=state.joints.replace(**joint_updates),
        thrusters=state.thrusters.replace(**thruster_updates),
        gravity=jnp.asarray(gravity),
    )
    state = refresh_collision_filter(state)

    env_params = data.get("env_params", {})
    known = {f.name for f in dataclasses.fields(SimParams)}
    params = SimParams(**{k: float(v) for k, v in env_params.items() if k in known})

    def extra(entries: list[dict], field: str, size: int, default: float, dtype) -> np.ndarray:
        out = np.full(size, default, dtype=dtype)
        if entries:
            out[: len(entries)] = [entry.get(field, default) for entry in entries]
        return out

    return KinetixLevel(
        state=state,
        sizes=target,
        params=params,
        polygon_roles=extra(polygons, "role", Pt, 0, np.int32),
        circle_roles=extra(circles, "role", target.num_circles, 0, np.int32),
        polygon_densities=extra(polygons, "density", Pt, 1.0, np.float32),
        circle_densities=extra(circles, "density", target.num_circles, 1.0, np.float32),
        motor_bindings=extra(joints, "motor_binding", target.num_joints, 0, np.int32),
        thruster_bindings=extra(thrusters, "thruster_binding", target.num_thrusters, 0, np.int32),
        frame_skip=int(static.get("frame_skip", 2)),
    )
