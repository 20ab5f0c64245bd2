"""Kinetix's JSON level files: loading (padded into any larger size), checking and saving.

This is also Impulse's own level format. A file holds Jax2D's state as separate polygon and circle lists
(array-of-structs, every slot included, inactive ones too), arrays encoded as objects keyed "0", "1", ..., plus the
task data Kinetix keeps inside the entries (shape roles and densities, motor and thruster bindings) and the
`env_params` / `static_env_params` it was made with; see the level-format section of the Kinetix digest.

Loading keeps the stored inverse masses and inertias (they encode Jax2D's mass conventions) and recomputes the
joint collision filter, as Kinetix does. The contact cache is read from the stored manifolds when the level keeps
its own size (Kinetix's files hold zeros there; a saved mid-episode state comes back exactly) and starts empty
when the level is padded into a larger size, as in Kinetix. Every problem with a file is reported as a
`LevelFileError` naming the file, the field and the problem; the scene is then checked with `validate_scene`.

Saving writes the same structure as Kinetix (key order included): `save(load(file))` reproduces every field the
loader reads, and `load(save(level))` gives back the level's arrays bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.arena import PIXELS_PER_METRE, SCREEN_PIXELS
from impulse.engine.levels.level import (
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    ROLE_NAMES,
    UNASSIGNED_LEVEL_ID,
    Level,
    level_id_words,
    with_content_id,
)
from impulse.engine.physics.building import empty_scene, refresh_collision_filter
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState
from impulse.engine.physics.validate import validate_scene

# Values Kinetix writes beside the scene; fixed in every size (see the digest's section on embedded params).
MAX_TIMESTEPS = 256
DENSE_REWARD_SCALE = 0.1
NUM_SHAPE_ROLES = 4
DOWNSCALE = 4
SOLVER_BATCH_SIZE = 16
MAX_SHAPE_SIZE = 2
# Kinetix's EnvParams declares these with integer defaults, so its files write them as JSON integers.
_INTEGER_PARAMS = ("clip_position", "clip_velocity", "clip_angular_velocity")


class LevelFileError(ValueError):
    """A level file is malformed, does not fit the requested size, or holds an invalid scene.

    `path` is the file and `problems` lists every problem found, each naming the field (e.g.
    "polygon[4].position missing").
    """

    def __init__(self, path: str | Path, problems: str | list[str]):
        problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__(str(path), problems)
        self.path = str(path)
        self.problems = problems

    def __str__(self) -> str:
        if len(self.problems) == 1:
            return f"{self.path}: {self.problems[0]}"
        listed = "\n  ".join(self.problems)
        return f"{self.path}: {len(self.problems)} problems:\n  {listed}"


class LevelDoesNotFit(LevelFileError):
    """A level file that does not fit the requested size (more slots than it allows, or another arena).

    `needs` holds the slot counts the level would need (the file's own, or the slots it uses when loaded with
    `compact`), so that a loader of a set can say which size each left-out level needs."""

    def __init__(self, path: str | Path, problems: str | list[str], needs: SceneSizes):
        super().__init__(path, problems)
        self.args = (*self.args, needs)  # so that a copy or a pickle is built with `needs` too
        self.needs = needs


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
    file_sizes: SceneSizes | None = None
    """The slot counts stored in the file (`sizes` is what it was loaded into)."""
    options: SolverOptions = SolverOptions()
    """The solver iterations and warm start the file asks for (its `num_solver_iterations` and
    `do_warm_starting`); schedule and backend are ours, left at their defaults."""

    @property
    def level(self) -> Level:
        """The scene and its task data as one pytree, roles and densities in body order; its id is the content
        hash, so the same file loaded twice is the same level."""
        return with_content_id(Level(
            state=self.state,
            roles=jnp.asarray(np.concatenate([self.polygon_roles, self.circle_roles]), jnp.int32),
            densities=jnp.asarray(np.concatenate([self.polygon_densities, self.circle_densities]), jnp.float32),
            motor_bindings=jnp.asarray(self.motor_bindings, jnp.int32),
            thruster_bindings=jnp.asarray(self.thruster_bindings, jnp.int32),
            level_id=jnp.asarray(level_id_words(UNASSIGNED_LEVEL_ID)),
        ))


# ---------------------------------------------------------------------------------------------------------------
# Field tables, in Kinetix's key order. Kind: "f" float32, "i" int32, "b" bool. Shape "V" = max polygon vertices.

_F, _I, _B = "f", "i", "b"
_VEC = (2,)

_SHAPE_FIELDS: tuple[tuple[str, str, tuple], ...] = (
    ("position", _F, _VEC),
    ("rotation", _F, ()),
    ("velocity", _F, _VEC),
    ("angular_velocity", _F, ()),
    ("inverse_mass", _F, ()),
    ("inverse_inertia", _F, ()),
    ("friction", _F, ()),
    ("restitution", _F, ()),
    ("collision_mode", _I, ()),
    ("active", _B, ()),
    ("n_vertices", _I, ()),
    ("vertices", _F, ("V", 2)),
    ("radius", _F, ()),
    ("role", _I, ()),
    ("density", _F, ()),
    ("highlighted", _B, ()),
)
_BODY_FIELDS = (
    "position", "rotation", "velocity", "angular_velocity", "inverse_mass", "inverse_inertia", "friction",
    "restitution", "collision_mode", "active",
)
# What the loader reads from each kind of shape; the rest (a polygon's radius, a circle's vertices, highlighted)
# are leftovers Kinetix writes and ignores.
_POLYGON_READS = (*_BODY_FIELDS, "n_vertices", "vertices", "role", "density")
_CIRCLE_READS = (*_BODY_FIELDS, "radius", "role", "density")

_JOINT_FIELDS: tuple[tuple[str, str, tuple], ...] = (
    ("a_index", _I, ()),
    ("b_index", _I, ()),
    ("a_relative_pos", _F, _VEC),
    ("b_relative_pos", _F, _VEC),
    ("global_position", _F, _VEC),
    ("active", _B, ()),
    ("acc_impulse", _F, _VEC),
    ("acc_r_impulse", _F, ()),
    ("motor_speed", _F, ()),
    ("motor_power", _F, ()),
    ("motor_on", _B, ()),
    ("motor_has_joint_limits", _B, ()),
    ("min_rotation", _F, ()),
    ("max_rotation", _F, ()),
    ("is_fixed_joint", _B, ()),
    ("rotation", _F, ()),
    ("motor_binding", _I, ()),
)
_THRUSTER_FIELDS: tuple[tuple[str, str, tuple], ...] = (
    ("object_index", _I, ()),
    ("relative_position", _F, _VEC),
    ("rotation", _F, ()),
    ("power", _F, ()),
    ("global_position", _F, _VEC),
    ("active", _B, ()),
    ("thruster_binding", _I, ()),
)
_MANIFOLD_FIELDS: tuple[tuple[str, str, tuple], ...] = (
    ("normal", _F, _VEC),
    ("penetration", _F, ()),
    ("collision_point", _F, _VEC),
    ("active", _B, ()),
    ("acc_impulse_normal", _F, ()),
    ("acc_impulse_tangent", _F, ()),
    ("restitution_velocity_target", _F, ()),
)
_MANIFOLD_READS = ("active", "acc_impulse_normal", "acc_impulse_tangent")
_DTYPES = {_F: np.float32, _I: np.int32, _B: np.bool_}


# ---------------------------------------------------------------------------------------------------------------
# Decoding


class _Malformed(ValueError):
    pass


def decode_arrays(value: Any) -> Any:
    """Turn Kinetix's {"0": a, "1": b} array encoding back into (nested) lists; other objects stay objects."""
    if isinstance(value, dict):
        if value and all(isinstance(k, str) and k.isdigit() for k in value):
            return _decode_array(value)
        return {k: decode_arrays(v) for k, v in value.items()}
    if isinstance(value, list):
        return [decode_arrays(v) for v in value]
    return value


def _decode_array(value: Any) -> Any:
    """A (nested) array in Kinetix's encoding as nested lists; objects that are not arrays are an error."""
    if isinstance(value, dict):
        keys = {str(i) for i in range(len(value))}
        if set(value) != keys:
            raise _Malformed("an object that is not an array (array keys must be \"0\", \"1\", ... without gaps)")
        return [_decode_array(value[str(i)]) for i in range(len(value))]
    if isinstance(value, list):
        return [_decode_array(v) for v in value]
    return value


def _numbers_only(value: Any) -> bool:
    if isinstance(value, list):
        return all(_numbers_only(v) for v in value)
    return isinstance(value, (int, float)) and value is not None


def _describe_shape(shape: tuple) -> str:
    return "a number" if shape == () else f"shape {list(shape)}"


def _parse_value(raw: Any, kind: str, shape: tuple) -> np.ndarray:
    """One field's value as an array of `kind` and exactly `shape`; raises _Malformed with the problem."""
    decoded = _decode_array(raw)
    if not _numbers_only(decoded):
        raise _Malformed(f"expected {'true/false' if kind == _B else _describe_shape(shape)} of numbers, "
                         f"got {json.dumps(raw)[:60]}")
    try:
        arr = np.asarray(decoded, dtype=np.float64)
    except OverflowError:
        raise _Malformed("number too large") from None
    except (ValueError, TypeError):
        raise _Malformed(f"wrong shape: expected {_describe_shape(shape)} (got a ragged array)") from None
    if arr.shape != shape:
        raise _Malformed(f"wrong shape: expected {_describe_shape(shape)}, got {_describe_shape(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise _Malformed("NaN or infinite value")
    if kind == _F:
        with np.errstate(over="ignore"):
            out = arr.astype(np.float32)
        if not np.all(np.isfinite(out)):
            raise _Malformed("value too large for float32")
        return out
    if kind == _I:
        if not np.all(arr == np.round(arr)) or np.any(np.abs(arr) >= 2**31):
            raise _Malformed(f"expected an integer, got {json.dumps(raw)[:60]}")
        return arr.astype(np.int32)
    if not np.all((arr == 0) | (arr == 1)):
        raise _Malformed(f"expected true or false, got {json.dumps(raw)[:60]}")
    return arr.astype(bool)


def _read_slots(
    env_state: dict, key: str, fields: tuple, reads: tuple[str, ...], vertices: int, problems: list[str]
) -> tuple[int, dict[str, np.ndarray]]:
    """(slot count, field -> [slots, ...] array) for one entity list; problems are appended, bad values left 0."""
    entries = env_state.get(key)
    if entries is None:
        problems.append(f"env_state.{key} missing")
        return 0, {}
    if not isinstance(entries, list):
        problems.append(f"env_state.{key}: expected a list of slot objects, got {type(entries).__name__}")
        return 0, {}
    spec = {name: (kind, tuple(vertices if d == "V" else d for d in shape)) for name, kind, shape in fields}
    columns = {name: np.zeros((len(entries), *spec[name][1]), _DTYPES[spec[name][0]]) for name in reads}
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict):
            problems.append(f"{key}[{i}]: expected an object, got {type(entry).__name__}")
            continue
        for name in reads:
            if name not in entry:
                problems.append(f"{key}[{i}].{name} missing")
                continue
            try:
                columns[name][i] = _parse_value(entry[name], *spec[name])
            except _Malformed as err:
                problems.append(f"{key}[{i}].{name}: {err}")
    return len(entries), columns


def _static_params(raw: Any, counts: dict[str, int], problems: list[str]) -> dict[str, int | bool]:
    """The file's static_env_params we use, with defaults; slot counts must agree with the entity lists."""
    out: dict[str, int | bool] = {
        "max_polygon_vertices": 4, "num_static_fixated_polys": 4, "num_solver_iterations": 10,
        "do_warm_starting": True, "frame_skip": 2,
    }
    if raw is None:
        return out
    if not isinstance(raw, dict):
        problems.append(f"static_env_params: expected an object, got {type(raw).__name__}")
        return out
    minimum = {"max_polygon_vertices": 3, "num_static_fixated_polys": 0, "num_solver_iterations": 1, "frame_skip": 1}
    for name, least in minimum.items():
        if name not in raw:
            continue
        value = _finite_number(raw[name])
        if value is None or value != int(value) or value < least:
            problems.append(f"static_env_params.{name}: expected an integer >= {least}, got {json.dumps(raw[name])}")
        else:
            out[name] = int(value)
    if "do_warm_starting" in raw:
        if isinstance(raw["do_warm_starting"], bool):
            out["do_warm_starting"] = raw["do_warm_starting"]
        else:
            problems.append(f"static_env_params.do_warm_starting: expected true or false, got "
                            f"{json.dumps(raw['do_warm_starting'])}")
    for name, count in counts.items():
        if name in raw and raw[name] != count:
            key = name.removeprefix("num_").removesuffix("s")
            problems.append(
                f"static_env_params.{name} is {json.dumps(raw[name])} but env_state.{key} has {count} slots"
            )
    return out


def _sim_params(raw: Any, problems: list[str]) -> SimParams:
    if raw is None:
        return SimParams()
    if not isinstance(raw, dict):
        problems.append(f"env_params: expected an object, got {type(raw).__name__}")
        return SimParams()
    values = {}
    for f in dataclasses.fields(SimParams):
        if f.name not in raw:
            continue
        value = _finite_number(raw[f.name])
        if value is None:
            problems.append(f"env_params.{f.name}: expected a finite number, got {json.dumps(raw[f.name])[:60]}")
        else:
            values[f.name] = value
    return SimParams(**values)


def _finite_number(value: Any) -> float | None:
    """`value` as a finite float, or None if it is not a JSON number (booleans are not numbers here)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _check_range(
    columns: dict[str, np.ndarray], key: str, field: str, low: int, high: int, what: str, problems: list[str]
) -> None:
    """Active slots of `key` must have `field` in [low, high]."""
    if field not in columns or "active" not in columns:
        return
    values, active = columns[field], columns["active"]
    for i in np.flatnonzero(active & ((values < low) | (values > high))):
        problems.append(f"{key}[{i}].{field}: {int(values[i])} is {what}")


def _manifold_cache(
    env_state: dict, tables_sizes: SceneSizes, problems: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The contact cache (normal impulse, tangent impulse, active) in engine slot order from the stored
    manifolds, or None when the file has none. Kinetix interleaves the two points of a polygon pair (pair i at
    entries 2i, 2i+1); the engine keeps every pair's point 0 first, then every pair's point 1."""
    tables = pair_tables(tables_sizes)
    expected = {
        "acc_rr_manifolds": (2 * tables.num_rr, "two per polygon pair"),
        "acc_cr_manifolds": (tables.num_cr, "one per circle-polygon pair"),
        "acc_cc_manifolds": (tables.num_cc, "one per circle pair"),
    }
    if not any(key in env_state for key in expected):
        return None
    parts = []
    for key, (count, why) in expected.items():
        n, columns = _read_slots(env_state, key, _MANIFOLD_FIELDS, _MANIFOLD_READS, 0, problems)
        if key in env_state and isinstance(env_state[key], list) and n != count:
            problems.append(f"env_state.{key}: {n} entries, expected {count} ({why})")
            return None
        if not columns:
            return None
        parts.append(columns)
    rr, cr, cc = parts
    order = np.concatenate([np.arange(0, 2 * tables.num_rr, 2), np.arange(1, 2 * tables.num_rr, 2)]).astype(int)

    def slots(field: str) -> np.ndarray:
        return np.concatenate([rr[field][order], cr[field], cc[field]])

    return slots("acc_impulse_normal"), slots("acc_impulse_tangent"), slots("active")


# ---------------------------------------------------------------------------------------------------------------
# Loading


MAX_LEVEL_FILE_BYTES = 64 * 2**20
"""The largest file the loader reads. Kinetix's largest levels (size L) are about 50 KB; the cap keeps a wrong path
(a dataset, a disk image) from filling memory before the format check can say it is not a level file."""

# Leading bytes of common binary formats, so that a file given by mistake is named for what it is.
_BINARY_SIGNATURES = (
    (b"\x89PNG\r\n\x1a\n", "a PNG image"),
    (b"\xff\xd8\xff", "a JPEG image"),
    (b"GIF8", "a GIF image"),
    (b"PK\x03\x04", "a zip archive"),
    (b"\x1f\x8b", "a gzip file"),
    (b"\x93NUMPY", "a NumPy array file"),
    (b"%PDF", "a PDF document"),
    (b"\x7fELF", "an executable"),
)
_UTF16_MARKS = (b"\xff\xfe", b"\xfe\xff")


def _read_bytes(path: Path) -> bytes:
    """The file's bytes, or a `LevelFileError` saying why it cannot be a level file.

    Opened without blocking and checked to be a regular file before reading, so that a folder, a pipe or a device
    (`/dev/zero`) gives an error instead of a hang, and capped at `MAX_LEVEL_FILE_BYTES`.
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except IsADirectoryError as err:
        raise LevelFileError(path, "is a folder, not a level file") from err
    except OSError as err:
        raise LevelFileError(path, f"cannot read the file: {err.strerror or err}") from err
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise LevelFileError(path, "is a folder, not a level file")
        if not stat.S_ISREG(info.st_mode):
            raise LevelFileError(path, "not a regular file (a device, pipe or socket): is it a level file?")
        if info.st_size > MAX_LEVEL_FILE_BYTES:
            raise LevelFileError(path, f"too large for a level file ({info.st_size:,} bytes; level files are at "
                                       f"most {MAX_LEVEL_FILE_BYTES:,})")
        chunks: list[bytes] = []
        size = 0
        while size <= MAX_LEVEL_FILE_BYTES and (chunk := os.read(fd, MAX_LEVEL_FILE_BYTES + 1 - size)):
            chunks.append(chunk)
            size += len(chunk)
        data = b"".join(chunks)
    except OSError as err:
        raise LevelFileError(path, f"cannot read the file: {err.strerror or err}") from err
    finally:
        os.close(fd)
    if len(data) > MAX_LEVEL_FILE_BYTES:  # grew while being read
        raise LevelFileError(path, f"too large for a level file (over {MAX_LEVEL_FILE_BYTES:,} bytes)")
    return data


def _decode_text(path: Path, data: bytes) -> str:
    """The file's text: UTF-8 (a leading byte-order mark is allowed), else a `LevelFileError` naming the first
    byte that is not UTF-8 and, for common binary formats, what the file seems to be."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        bad = err.object[err.start]
        offset = err.start + (3 if data.startswith(b"\xef\xbb\xbf") else 0)
        kind = next((name for magic, name in _BINARY_SIGNATURES if data.startswith(magic)), None)
        if kind is not None:
            advice = f"it looks like {kind}, not a level file"
        elif data.startswith(_UTF16_MARKS):
            advice = "it looks like UTF-16 text: save it as UTF-8"
        else:
            advice = "is it a level file?"
        raise LevelFileError(path, f"not a UTF-8 text file (byte 0x{bad:02x} at offset {offset}): {advice}") from err


def _parse_json(path: Path, text: str) -> Any:
    """The JSON value in `text`, or a `LevelFileError` with json's message (line and column) and, when the text
    ends where the error is, a hint that the file was cut short."""
    if not text.strip():
        what = "empty file" if not text else "the file holds only blank space"
        raise LevelFileError(path, f"{what}: a level file holds a JSON object")
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        truncated = err.pos >= len(text.rstrip())
        hint = "; the text ends there: is the file cut short?" if truncated else ""
        raise LevelFileError(path, f"not valid JSON: {err}{hint}") from err
    except RecursionError as err:
        raise LevelFileError(path, "not valid JSON: nested too deeply to read") from err
    except ValueError as err:  # e.g. an integer of more digits than Python converts
        raise LevelFileError(path, f"not valid JSON: {str(err).partition(';')[0]}") from err


def _read_json(path: Path) -> dict:
    """The file's top-level JSON object holding `env_state`; every way a file can fail to be one (unreadable, a
    folder, binary or non-UTF-8, empty, cut short, not JSON, not an object) is a one-line `LevelFileError`."""
    raw = _parse_json(path, _decode_text(path, _read_bytes(path)))
    if not isinstance(raw, dict):
        raise LevelFileError(path, f"not a level file: the top level must be an object, got {type(raw).__name__}")
    if not isinstance(raw.get("env_state"), dict):
        raise LevelFileError(path, "not a level file: env_state missing or not an object")
    return raw


def load_kinetix_level(
    path: str | Path, sizes: SceneSizes | None = None, *, validate: bool = True, compact: bool = False
) -> KinetixLevel:
    """Load a level file, in its own size or padded into `sizes` (which must be at least as large).

    Padding adds inactive slots; circles move up by the number of polygon slots added, and joint and thruster
    body indices follow them. Raises `LevelFileError` for a malformed file, one too large for `sizes`, or (with
    `validate`, the default) a scene that `validate_scene` rejects; tools that want to show such a scene anyway
    pass `validate=False` and call `validate_scene` themselves.

    A Kinetix file holds every slot of its size, used or not, so an M file is "too large" for S however few
    shapes it uses. With `compact`, a file larger than `sizes` is first cut to the slots it uses
    (`used_slots`) and loads when those fit: moving a level into a smaller size is then an explicit choice.
    """
    path = Path(path)
    return level_from_document(_read_json(path), sizes, validate=validate, source=path, compact=compact)


def load_level_document(document: Any, sizes: SceneSizes | None = None) -> Level:
    """The level of a level file's JSON object received whole (a level a person sends into a running curriculum),
    in `sizes`, validated; ValueError (a `LevelFileError`) naming every problem otherwise."""
    source = "the level sent"
    if not isinstance(document, dict):
        raise LevelFileError(source, f"not a level file: the top level must be an object, got "
                                     f"{type(document).__name__}")
    if not isinstance(document.get("env_state"), dict):
        raise LevelFileError(source, "not a level file: env_state missing or not an object")
    return level_from_document(document, sizes, source=source).level


def level_from_document(
    raw: dict, sizes: SceneSizes | None = None, *, validate: bool = True, source: str | Path = "the level",
    compact: bool = False,
) -> KinetixLevel:
    """`load_kinetix_level` of a level file's JSON object (`raw`, whose `env_state` is an object); problems are
    reported as those of `source`."""
    path = source
    env_state = raw["env_state"]
    problems: list[str] = []

    # Slot counts first: the vertex count (from static_env_params) shapes the polygon entries.
    counts = {}
    for key in ("polygon", "circle", "joint", "thruster"):
        entries = env_state.get(key)
        counts[f"num_{key}s"] = len(entries) if isinstance(entries, list) else 0
    static = _static_params(raw.get("static_env_params"), counts, problems)
    V = int(static["max_polygon_vertices"])
    P, polygons = _read_slots(env_state, "polygon", _SHAPE_FIELDS, _POLYGON_READS, V, problems)
    C, circles = _read_slots(env_state, "circle", _SHAPE_FIELDS, _CIRCLE_READS, V, problems)
    J, joints = _read_slots(env_state, "joint", _JOINT_FIELDS, tuple(f[0] for f in _JOINT_FIELDS), V, problems)
    T, thrusters = _read_slots(
        env_state, "thruster", _THRUSTER_FIELDS, tuple(f[0] for f in _THRUSTER_FIELDS), V, problems
    )
    gravity = np.array([0.0, -9.81], np.float32)
    if "gravity" not in env_state:
        problems.append("env_state.gravity missing")
    else:
        try:
            gravity = _parse_value(env_state["gravity"], _F, _VEC)
        except _Malformed as err:
            problems.append(f"env_state.gravity: {err}")
    params = _sim_params(raw.get("env_params"), problems)

    role_text = f"not a role ({', '.join(f'{i} {name}' for i, name in enumerate(ROLE_NAMES))})"
    for key, columns in (("polygon", polygons), ("circle", circles)):
        _check_range(columns, key, "role", 0, len(ROLE_NAMES) - 1, role_text, problems)
    _check_range(joints, "joint", "motor_binding", 0, NUM_MOTOR_BINDINGS - 1,
                 f"out of range (motor bindings are 0..{NUM_MOTOR_BINDINGS - 1})", problems)
    _check_range(thrusters, "thruster", "thruster_binding", 0, NUM_THRUSTER_BINDINGS - 1,
                 f"out of range (thruster bindings are 0..{NUM_THRUSTER_BINDINGS - 1})", problems)
    index_text = f"out of range (the file has {P} polygons and {C} circles: body indices 0..{P + C - 1})"
    for field in ("a_index", "b_index"):
        _check_range(joints, "joint", field, 0, P + C - 1, index_text, problems)
    _check_range(thrusters, "thruster", "object_index", 0, P + C - 1, index_text, problems)
    if problems:
        raise LevelFileError(path, problems)

    S = int(static["num_static_fixated_polys"])
    if S > P:
        raise LevelFileError(path, f"static_env_params.num_static_fixated_polys is {S} but the file has {P} polygons")
    file_sizes = SceneSizes(
        num_polygons=P, num_circles=C, num_joints=J, num_thrusters=T, max_polygon_vertices=V, num_static_polygons=S,
    )
    options = SolverOptions(
        iterations=int(static["num_solver_iterations"]), warm_starting=bool(static["do_warm_starting"])
    )
    target = sizes or file_sizes
    cache = _manifold_cache(env_state, file_sizes, problems)
    if problems:
        raise LevelFileError(path, problems)
    layout = file_sizes
    if compact and not file_sizes.fits_in(target):
        layout, (polygons, circles, joints, thrusters) = used_slots(file_sizes, polygons, circles, joints, thrusters)
        P, C = layout.num_polygons, layout.num_circles
        cache = None  # the contact cache is laid out by the file's slots
    if not layout.fits_in(target):
        raise LevelDoesNotFit(path, _does_not_fit(layout, target, compacted=layout is not file_sizes), layout)

    state = _build_state(target, P, C, polygons, circles, joints, thrusters, gravity, cache, layout)
    if validate:
        found = validate_scene(state)
        if found:
            raise LevelFileError(path, [f"invalid scene: {p}" for p in found])

    def task(columns: dict, field: str, size: int, default, dtype) -> np.ndarray:
        out = np.full(size, default, dtype=dtype)
        if field in columns:
            out[: len(columns[field])] = columns[field]
        return out

    return KinetixLevel(
        state=state,
        sizes=target,
        params=params,
        polygon_roles=task(polygons, "role", target.num_polygons, 0, np.int32),
        circle_roles=task(circles, "role", target.num_circles, 0, np.int32),
        polygon_densities=task(polygons, "density", target.num_polygons, 1.0, np.float32),
        circle_densities=task(circles, "density", target.num_circles, 1.0, np.float32),
        motor_bindings=task(joints, "motor_binding", target.num_joints, 0, np.int32),
        thruster_bindings=task(thrusters, "thruster_binding", target.num_thrusters, 0, np.int32),
        frame_skip=int(static["frame_skip"]),
        file_sizes=file_sizes,
        options=options,
    )


def _does_not_fit(file_sizes: SceneSizes, target: SceneSizes, *, compacted: bool = False) -> str:
    if file_sizes.num_static_polygons != target.num_static_polygons:
        return (f"the file has {file_sizes.num_static_polygons} static arena polygons but the size expects "
                f"{target.num_static_polygons}")
    names = ("num_polygons", "num_circles", "num_joints", "num_thrusters", "max_polygon_vertices")
    over = [
        f"{getattr(file_sizes, n)} {n.removeprefix('num_').replace('_', ' ')} (the size allows {getattr(target, n)})"
        for n in names
        if getattr(file_sizes, n) > getattr(target, n)
    ]
    return f"too large for the size: the {'level uses' if compacted else 'file has'} " + ", ".join(over)


def used_slots(
    file_sizes: SceneSizes, polygons: dict, circles: dict, joints: dict, thrusters: dict
) -> tuple[SceneSizes, tuple[dict, dict, dict, dict]]:
    """A file's slot columns cut to what the level uses, with the slot counts that remain.

    Kept: the static arena polygons, every active shape and every shape an active joint or thruster names (an
    inactive one stays so that the scene's own validation, not this cut, reports it), and the active joints and
    thrusters. Shapes keep their order (polygons, then circles) and joint and thruster body indices are renumbered
    to the kept shapes."""
    P, S = file_sizes.num_polygons, file_sizes.num_static_polygons
    joint_on = joints["active"].astype(bool) if joints else np.zeros(0, bool)
    thruster_on = thrusters["active"].astype(bool) if thrusters else np.zeros(0, bool)
    named = np.zeros(P + file_sizes.num_circles, bool)
    for column in (joints.get("a_index"), joints.get("b_index")):
        if column is not None:
            named[column[joint_on]] = True
    if thrusters:
        named[thrusters["object_index"][thruster_on]] = True
    keep_polygon = (polygons["active"].astype(bool) | named[:P]) if polygons else np.zeros(0, bool)
    keep_polygon[:S] = True
    keep_circle = (circles["active"].astype(bool) | named[P:]) if circles else np.zeros(0, bool)
    renumber = np.cumsum(np.concatenate([keep_polygon, keep_circle])) - 1

    def cut(columns: dict, keep: np.ndarray, indices: tuple[str, ...] = ()) -> dict:
        return {name: renumber[column[keep]].astype(np.int32) if name in indices else column[keep]
                for name, column in columns.items()}

    kept = (cut(polygons, keep_polygon), cut(circles, keep_circle), cut(joints, joint_on, ("a_index", "b_index")),
            cut(thrusters, thruster_on, ("object_index",)))
    layout = dataclasses.replace(
        file_sizes, num_polygons=int(keep_polygon.sum()), num_circles=int(keep_circle.sum()),
        num_joints=int(joint_on.sum()), num_thrusters=int(thruster_on.sum()),
    )
    return layout, kept


def _build_state(
    target: SceneSizes,
    P: int,
    C: int,
    polygons: dict,
    circles: dict,
    joints: dict,
    thrusters: dict,
    gravity: np.ndarray,
    cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    file_sizes: SceneSizes,
) -> SimState:
    Pt = target.num_polygons
    host = jax.tree.map(np.array, _empty_scene_host(target))

    def shift(index: np.ndarray) -> np.ndarray:
        # Circles move up when polygon slots are added in front of them.
        return np.where(index >= P, index + (Pt - P), index).astype(np.int32)

    bodies = {}
    for field in _BODY_FIELDS:
        arr = getattr(host.bodies, field)
        if P:
            arr[:P] = polygons[field]
        if C:
            arr[Pt : Pt + C] = circles[field]
        bodies[field] = arr
    vertices, n_vertices, radius = host.polygon_vertices, host.polygon_n_vertices, host.circle_radius
    if P:
        V = polygons["vertices"].shape[1]
        vertices[:P] = 0.0
        vertices[:P, :V] = polygons["vertices"]
        n_vertices[:P] = polygons["n_vertices"]
    if C:
        radius[:C] = circles["radius"]
    joint_fields = {}
    for field in vars(host.joints):
        arr = getattr(host.joints, field)
        if len(joints.get(field, ())):
            arr[: len(joints[field])] = shift(joints[field]) if field in ("a_index", "b_index") else joints[field]
        joint_fields[field] = arr
    thruster_fields = {}
    for ours in vars(host.thrusters):
        theirs = "object_index" if ours == "body_index" else ours
        arr = getattr(host.thrusters, ours)
        if len(thrusters.get(theirs, ())):
            column = thrusters[theirs]
            arr[: len(column)] = shift(column) if ours == "body_index" else column
        thruster_fields[ours] = arr
    contacts = host.contacts
    same_layout = (P, C, file_sizes.num_static_polygons) == (Pt, target.num_circles, target.num_static_polygons)
    if cache is not None and same_layout:
        contacts = contacts.replace(normal_impulse=cache[0], tangent_impulse=cache[1], active=cache[2])
    host = host.replace(
        bodies=host.bodies.replace(**bodies),
        polygon_vertices=vertices,
        polygon_n_vertices=n_vertices,
        circle_radius=radius,
        joints=host.joints.replace(**joint_fields),
        thrusters=host.thrusters.replace(**thruster_fields),
        contacts=contacts,
        gravity=gravity,
    )
    return _refresh_collision_filter(jax.device_put(host))


# Jitted once per size: run eagerly, these two cost a compile per primitive the first time a size is seen.
_refresh_collision_filter = jax.jit(refresh_collision_filter)


@functools.cache
def _empty_scene_host(sizes: SceneSizes) -> SimState:
    return jax.tree.map(np.asarray, jax.jit(empty_scene, static_argnums=0)(sizes))


def level_file_problems(path: str | Path, sizes: SceneSizes | None = None) -> list[str]:
    """Every problem with a level file (format, fit into `sizes`, scene validity); empty when it is valid."""
    try:
        level = load_kinetix_level(path, sizes, validate=False)
    except LevelFileError as err:
        return list(err.problems)
    return [f"invalid scene: {p}" for p in validate_scene(level.state)]


# ---------------------------------------------------------------------------------------------------------------
# Saving


def _encode(value: np.ndarray) -> Any:
    """A host array in Kinetix's encoding: nested {"0": ..., "1": ...} objects around plain JSON scalars."""
    if value.ndim == 0:
        if value.dtype == np.bool_:
            return bool(value)
        if value.dtype.kind in "iu":
            return int(value)
        return float(value)
    return {str(i): _encode(value[i]) for i in range(value.shape[0])}


def level_to_json_dict(
    level: Level,
    sizes: SceneSizes,
    params: SimParams | None = None,
    frame_skip: int = 2,
    options: SolverOptions | None = None,
) -> dict[str, Any]:
    """A level as the JSON object of a Kinetix level file (three keys: env_state, env_params, static_env_params).
    `options` gives the solver iterations and warm start the file records (default: Kinetix's)."""
    params = SimParams() if params is None else params
    options = SolverOptions() if options is None else options
    host: Level = jax.tree.map(np.asarray, level)
    s = host.state
    P, C, J, T, V = (sizes.num_polygons, sizes.num_circles, sizes.num_joints, sizes.num_thrusters,
                     sizes.max_polygon_vertices)
    tables = pair_tables(sizes)
    expected = {
        "roles": (host.roles.shape, (P + C,)),
        "motor_bindings": (host.motor_bindings.shape, (J,)),
        "thruster_bindings": (host.thruster_bindings.shape, (T,)),
        "state.polygon_vertices": (s.polygon_vertices.shape, (P, V, 2)),
        "state.circle_radius": (s.circle_radius.shape, (C,)),
        "state.contacts": (s.contacts.active.shape, (tables.num_contacts,)),
    }
    wrong = [f"{name} has shape {got}, expected {want}" for name, (got, want) in expected.items() if got != want]
    if wrong:
        raise ValueError("level does not match the sizes (a batch of levels must be saved one by one): "
                         + "; ".join(wrong))
    if frame_skip < 1:
        raise ValueError(f"frame_skip must be >= 1, got {frame_skip}")
    b = s.bodies
    zero_vertices = np.zeros((V, 2), np.float32)

    def shape_entry(body: int, n_vertices: int, vertices: np.ndarray, radius: float) -> dict[str, Any]:
        entry = {field: _encode(getattr(b, field)[body]) for field in _BODY_FIELDS}
        entry["n_vertices"] = int(n_vertices)
        entry["vertices"] = _encode(vertices)
        entry["radius"] = float(radius)
        entry["role"] = int(host.roles[body])
        entry["density"] = float(host.densities[body])
        entry["highlighted"] = False
        return entry

    polygons = [shape_entry(i, s.polygon_n_vertices[i], s.polygon_vertices[i], 0.0) for i in range(P)]
    circles = [shape_entry(P + i, 0, zero_vertices, s.circle_radius[i]) for i in range(C)]

    def slot_entry(group: Any, fields: tuple, slot: int, rename: dict[str, str], extra: dict) -> dict[str, Any]:
        entry = {}
        for name, _, _ in fields:
            if name in extra:
                entry[name] = int(extra[name][slot])
            else:
                entry[name] = _encode(getattr(group, rename.get(name, name))[slot])
        return entry

    joints = [
        slot_entry(s.joints, _JOINT_FIELDS, j, {}, {"motor_binding": host.motor_bindings}) for j in range(J)
    ]
    thrusters = [
        slot_entry(s.thrusters, _THRUSTER_FIELDS, t, {"object_index": "body_index"},
                   {"thruster_binding": host.thruster_bindings})
        for t in range(T)
    ]
    collides = _collision_matrix(s.joints, P + C)

    cache = s.contacts

    def manifold(slot: int) -> dict[str, Any]:
        return {
            "normal": {"0": 0.0, "1": 0.0},
            "penetration": 0.0,
            "collision_point": {"0": 0.0, "1": 0.0},
            "active": bool(cache.active[slot]),
            "acc_impulse_normal": float(cache.normal_impulse[slot]),
            "acc_impulse_tangent": float(cache.tangent_impulse[slot]),
            "restitution_velocity_target": 0.0,
        }

    n_rr = tables.num_rr
    rr = [manifold(pair + point * n_rr) for pair in range(n_rr) for point in (0, 1)]
    cr = [manifold(2 * n_rr + k) for k in range(tables.num_cr)]
    cc = [manifold(2 * n_rr + tables.num_cr + k) for k in range(tables.num_cc)]

    env_params: dict[str, Any] = {}
    for f in dataclasses.fields(SimParams):
        value = float(getattr(params, f.name))
        env_params[f.name] = int(value) if f.name in _INTEGER_PARAMS and value.is_integer() else value
    env_params.update(
        max_timesteps=MAX_TIMESTEPS, pixels_per_unit=PIXELS_PER_METRE, dense_reward_scale=DENSE_REWARD_SCALE,
        num_shape_roles=NUM_SHAPE_ROLES,
    )
    static_env_params = {
        "num_polygons": P,
        "num_circles": C,
        "num_joints": J,
        "num_thrusters": T,
        "max_polygon_vertices": V,
        "num_solver_iterations": options.iterations,
        "solver_batch_size": SOLVER_BATCH_SIZE,
        "do_warm_starting": bool(options.warm_starting),
        "num_static_fixated_polys": sizes.num_static_polygons,
        "screen_dim": {"0": SCREEN_PIXELS, "1": SCREEN_PIXELS},
        "downscale": DOWNSCALE,
        "frame_skip": int(frame_skip),
        "max_shape_size": MAX_SHAPE_SIZE,
        "num_motor_bindings": NUM_MOTOR_BINDINGS,
        "num_thruster_bindings": NUM_THRUSTER_BINDINGS,
    }
    return {
        "env_state": {
            "polygon": polygons,
            "circle": circles,
            "joint": joints,
            "thruster": thrusters,
            "collision_matrix": _encode(collides),
            "acc_rr_manifolds": rr,
            "acc_cr_manifolds": cr,
            "acc_cc_manifolds": cc,
            "gravity": _encode(s.gravity),
        },
        "env_params": env_params,
        "static_env_params": static_env_params,
    }


def _collision_matrix(joints: Any, num_bodies: int) -> np.ndarray:
    """[N, N] bool, Kinetix's collision matrix: two shapes may collide unless they are the same shape or linked
    through a chain of active joints (what `refresh_collision_filter` computes per pair, here in numpy)."""
    parent = list(range(num_bodies))

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    a, b, active = np.asarray(joints.a_index), np.asarray(joints.b_index), np.asarray(joints.active)
    for i, j in zip(a[active], b[active]):
        if 0 <= i < num_bodies and 0 <= j < num_bodies:
            parent[root(int(j))] = root(int(i))
    roots = np.array([root(i) for i in range(num_bodies)])
    return roots[:, None] != roots[None, :]


def save_kinetix_level(
    path: str | Path,
    level: Level,
    sizes: SceneSizes,
    params: SimParams | None = None,
    frame_skip: int = 2,
    options: SolverOptions | None = None,
) -> Path:
    """Write `level` (one level of `sizes`) as a Kinetix JSON file; the file is replaced atomically."""
    path = Path(path)
    text = json.dumps(level_to_json_dict(level, sizes, params, frame_skip, options))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as out:
            out.write(text)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; a level file is an ordinary, shareable file
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
