"""Kinetix's offline (behaviour-cloning) datasets: reading them as our levels, actions and masks.

Kinetix 3.0.x keeps offline data as a zarr group (format 2) whose arrays are shards. A shard is a 1-D array of
records (a numpy structured dtype); a record holds an `action`, its `action_mask` (the action dimensions a motor or
thruster of the level is bound to), optionally `mask` and `level_rngs`, and the full environment state the action
was taken in, one field per leaf named by its path: `env_state/polygon/position`, `env_state/joint/motor_speed`,
`env_state/polygon_shape_roles`, `env_state/acc_rr_manifolds/active`, `env_state/timestep`, ... A trajectory
dataset holds one trajectory per record instead: every field carries a leading [T, 1] (steps, one environment)
and a `done` field is added. Kinetix reads shards in name order.

The environment state of a record is what a Kinetix level file stores under `env_state`, laid out as arrays
(struct-of-arrays) rather than as one object per slot, with the task data (roles, densities, bindings) beside
the slots rather than inside them. Each record is therefore rewritten as a level document and loaded with the
level-file loader (`kinetix_json.level_from_document`): one parser, the same checks and the same padding into
larger sizes. The mid-episode contact cache comes back too (the loader reads stored manifolds).

zarr 3 (the zarr of our environment) cannot open these arrays: it has no data type for structured records with
array-shaped fields, which every Kinetix record has. The shards are read here from the format-2 storage layout
instead (`.zgroup`; per array a `.zarray` JSON and one file per chunk, compressed by the numcodecs codec the
metadata names), as the Zarr storage specification version 2 documents it. Directory stores only.

Every problem is a `LevelFileError` naming the dataset (and shard or record) and the problem.
"""

from __future__ import annotations

import base64
import functools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.levels.kinetix_json import LevelFileError, level_from_document
from impulse.engine.levels.level import Level
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState

# Per-slot fields of each entity list in a record (Kinetix's names), as the level document needs them.
_BODY_FIELDS = (
    "position", "rotation", "velocity", "angular_velocity", "inverse_mass", "inverse_inertia", "friction",
    "restitution", "collision_mode", "active",
)
_SLOT_FIELDS: dict[str, tuple[str, ...]] = {
    "polygon": (*_BODY_FIELDS, "n_vertices", "vertices"),
    "circle": (*_BODY_FIELDS, "radius"),
    "joint": (
        "a_index", "b_index", "a_relative_pos", "b_relative_pos", "global_position", "active", "acc_impulse",
        "acc_r_impulse", "motor_speed", "motor_power", "motor_on", "motor_has_joint_limits", "min_rotation",
        "max_rotation", "is_fixed_joint", "rotation",
    ),
    "thruster": ("object_index", "relative_position", "rotation", "power", "global_position", "active"),
}
# Task data kept beside the slots in a record and inside each slot object in a level file: (entity, record field,
# level-file key).
_TASK_FIELDS = (
    ("polygon", "polygon_shape_roles", "role"),
    ("polygon", "polygon_densities", "density"),
    ("circle", "circle_shape_roles", "role"),
    ("circle", "circle_densities", "density"),
    ("joint", "motor_bindings", "motor_binding"),
    ("thruster", "thruster_bindings", "thruster_binding"),
)
_MANIFOLD_KINDS = ("acc_rr_manifolds", "acc_cr_manifolds", "acc_cc_manifolds")
_MANIFOLD_FIELDS = ("active", "acc_impulse_normal", "acc_impulse_tangent")
_STATE = "env_state/"

REQUIRED_FIELDS: tuple[str, ...] = (
    "action",
    "action_mask",
    *(f"{_STATE}{entity}/{field}" for entity, fields in _SLOT_FIELDS.items() for field in fields),
    *(f"{_STATE}{field}" for _, field, _ in _TASK_FIELDS),
    *(f"{_STATE}{kind}/{field}" for kind in _MANIFOLD_KINDS for field in _MANIFOLD_FIELDS),
    f"{_STATE}gravity",
    f"{_STATE}timestep",
)
"""The record fields this reader needs (Kinetix's own reader needs these and a few it keeps but we do not use:
the collision matrix, highlights, `motor_auto`, `last_distance`, manifold geometry)."""


class KinetixTransitions(NamedTuple):
    """An offline dataset as transitions, in Kinetix's reading order (shards by name, records in order, a
    trajectory's steps in order); N is the number of transitions."""

    levels: Level
    """[N] the state each action was taken in, as our levels (in the `sizes` asked for)."""
    action: np.ndarray
    """[N, action_dim] the actions as stored (int32 for multi-discrete and discrete data, float32 continuous)."""
    action_mask: np.ndarray
    """[N, action_dim] bool: the action dimensions some motor or thruster of the level is bound to."""
    mask: np.ndarray
    """[N] bool: Kinetix's valid-transition flag (all true where a dataset stores none, as in trajectories)."""
    done: np.ndarray | None
    """[N] bool: the episode ended after this action; None for flat (transition) datasets."""
    timestep: np.ndarray
    """[N] int32: the agent step of the state within its episode."""
    trajectory_length: int | None
    """T for a trajectory dataset (transitions reshape to [N // T, T]); None for flat datasets."""


# ---------------------------------------------------------------------------------------------------------------
# The zarr format-2 storage layout


def _read_json(path: Path, dataset: Path, what: str) -> dict:
    try:
        value = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise LevelFileError(dataset, f"{what}: unreadable ({err})") from None
    if not isinstance(value, dict):
        raise LevelFileError(dataset, f"{what}: expected a JSON object")
    return value


def _shard_names(dataset: Path) -> list[str]:
    """The group's arrays (its shards), by name; raises if `dataset` is not a zarr format-2 group."""
    if not dataset.is_dir():
        raise LevelFileError(dataset, "not a zarr group: no such folder" if not dataset.exists()
                             else "not a zarr group: not a folder (only directory stores are read)")
    if not (dataset / ".zgroup").is_file():
        if (dataset / "zarr.json").is_file():
            raise LevelFileError(dataset, "a zarr format 3 store; Kinetix's offline data is zarr format 2")
        raise LevelFileError(dataset, "not a zarr group: no .zgroup file")
    meta = _read_json(dataset / ".zgroup", dataset, ".zgroup")
    if meta.get("zarr_format") != 2:
        raise LevelFileError(dataset, f".zgroup: zarr_format is {meta.get('zarr_format')!r}, expected 2")
    names = sorted(p.name for p in dataset.iterdir() if (p / ".zarray").is_file())
    if not names:
        raise LevelFileError(dataset, "the zarr group holds no arrays (shards)")
    return names


def _record_dtype(spec: Any) -> np.dtype:
    """A numpy structured dtype from the `.zarray` form: a list of [name, type string] or [name, type, shape]."""
    if not isinstance(spec, list) or not spec:
        raise ValueError(f"dtype {json.dumps(spec)[:60]} is not a record (structured) type")
    fields = []
    for entry in spec:
        if not (isinstance(entry, list) and len(entry) in (2, 3) and isinstance(entry[0], str)
                and isinstance(entry[1], str)):
            raise ValueError(f"dtype field {json.dumps(entry)[:60]} is not [name, type] or [name, type, shape]")
        fields.append((entry[0], entry[1], tuple(entry[2])) if len(entry) == 3 else (entry[0], entry[1]))
    return np.dtype(fields)


def _codec(config: Any) -> Any:
    try:
        import numcodecs  # zarr's codec library, installed with zarr
    except ImportError:
        raise ImportError("reading Kinetix offline data needs numcodecs (install zarr)") from None
    return numcodecs.get_codec(dict(config))


def _read_shard(dataset: Path, name: str) -> np.ndarray:
    """All records of one shard as a structured array."""
    where = f"shard {name}"
    meta = _read_json(dataset / name / ".zarray", dataset, f"{where}/.zarray")
    try:
        if meta.get("zarr_format") != 2:
            raise ValueError(f"zarr_format is {meta.get('zarr_format')!r}, expected 2")
        shape, chunks = meta.get("shape"), meta.get("chunks")
        if not (isinstance(shape, list) and len(shape) == 1 and isinstance(chunks, list) and len(chunks) == 1):
            raise ValueError(f"shape {shape} / chunks {chunks}: a shard is a 1-D array of records")
        dtype = _record_dtype(meta.get("dtype"))
        compressor = _codec(meta["compressor"]) if meta.get("compressor") else None
        filters = [_codec(f) for f in meta.get("filters") or []]
    except (ValueError, TypeError, KeyError) as err:
        raise LevelFileError(dataset, f"{where}/.zarray: {err}") from None
    count, per_chunk = int(shape[0]), int(chunks[0])
    fill = np.zeros(1, dtype)
    if isinstance(meta.get("fill_value"), str):  # structured fill values are the base64 of one record's bytes
        raw = base64.b64decode(meta["fill_value"])
        if len(raw) == dtype.itemsize:
            fill = np.frombuffer(raw, dtype, count=1)
    records = np.empty(count, dtype)
    for index in range(-(-count // per_chunk) if per_chunk else 0):
        start = index * per_chunk
        stop = min(start + per_chunk, count)
        chunk_path = dataset / name / str(index)
        if not chunk_path.is_file():  # zarr leaves chunks that hold only the fill value unwritten
            records[start:stop] = fill[0]
            continue
        data: Any = chunk_path.read_bytes()
        try:
            if compressor is not None:
                data = compressor.decode(data)
            for codec in reversed(filters):
                data = codec.decode(data)
            chunk = np.frombuffer(memoryview(data).cast("B"), dtype)
        except Exception as err:  # codecs raise their own error types
            raise LevelFileError(dataset, f"{where} chunk {index}: cannot decode ({err})") from None
        if len(chunk) != per_chunk:
            raise LevelFileError(dataset, f"{where} chunk {index}: {len(chunk)} records, expected {per_chunk}")
        records[start:stop] = chunk[: stop - start]
    return records


# ---------------------------------------------------------------------------------------------------------------
# Records -> transitions


def _columns(dataset: Path, name: str, records: np.ndarray) -> tuple[dict[str, np.ndarray], int | None]:
    """Field -> [transitions, ...] arrays of one shard, trajectories flattened to their steps; (columns, T)."""
    names = records.dtype.names or ()
    missing = [f for f in REQUIRED_FIELDS if f not in names]
    if missing:
        listed = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        raise LevelFileError(dataset, f"shard {name}: field{'s' if len(missing) > 1 else ''} {listed} missing")
    if "done" not in names:
        return {field: records[field] for field in names}, None
    if not records.dtype["done"].shape:
        raise LevelFileError(dataset, f"shard {name}: field done has no time axis; a trajectory record's fields "
                                      "are [steps, 1, ...]")
    length = records.dtype["done"].shape[0]
    columns = {}
    for field in names:
        value = records[field]
        if value.shape[1:3] != (length, 1):
            raise LevelFileError(dataset, f"shard {name}: trajectory field {field} has shape {value.shape[1:]}, "
                                          f"expected ({length}, 1, ...) (steps, one environment)")
        columns[field] = value.reshape(len(records) * length, *value.shape[3:])
    return columns, length


def _document(columns: dict[str, np.ndarray], index: int, sizes: SceneSizes) -> dict:
    """Record `index` as a Kinetix level document (one object per slot, task data inside the slots)."""

    def column(field: str) -> np.ndarray:
        return columns[f"{_STATE}{field}"][index]

    env_state: dict[str, Any] = {}
    for entity, fields in _SLOT_FIELDS.items():
        values = {field: column(f"{entity}/{field}") for field in fields}
        count = len(values["active"])
        env_state[entity] = [{field: value[slot].tolist() for field, value in values.items()} for slot in range(count)]
    for entity, field, key in _TASK_FIELDS:
        for slot, value in zip(env_state[entity], column(field).tolist()):
            slot[key] = value
    for kind in _MANIFOLD_KINDS:
        values = {field: column(f"{kind}/{field}") for field in _MANIFOLD_FIELDS}
        # Polygon pairs hold two contact points ([pairs, 2]); a level file lists them one after the other.
        values = {field: value.reshape(-1) for field, value in values.items()}
        env_state[kind] = [{field: value[i].tolist() for field, value in values.items()}
                           for i in range(len(values["active"]))]
    env_state["gravity"] = column("gravity").tolist()
    vertices = column("polygon/vertices")
    static = {"num_static_fixated_polys": sizes.num_static_polygons}
    if vertices.ndim == 3:
        static["max_polygon_vertices"] = vertices.shape[1]
    return {"env_state": env_state, "static_env_params": static}


def read_kinetix_offline(path: str | Path, sizes: SceneSizes) -> KinetixTransitions:
    """Every transition of a Kinetix offline dataset (a flat or a trajectory zarr group), its states as levels in
    `sizes` (a state from a smaller size is padded into it, as level files are).

    Raises `LevelFileError` naming the dataset for a folder that is not a zarr format-2 group, a shard that is not
    a 1-D record array or lacks a field of `REQUIRED_FIELDS`, and naming the shard and record for a state that
    does not fit `sizes` or is not a valid scene.
    """
    dataset = Path(path)
    levels: list[Level] = []
    parts: dict[str, list[np.ndarray]] = {"action": [], "action_mask": [], "mask": [], "done": [], "timestep": []}
    lengths = set()
    for name in _shard_names(dataset):
        records = _read_shard(dataset, name)
        if len(records) == 0:  # Kinetix skips empty shards too
            continue
        columns, length = _columns(dataset, name, records)
        lengths.add(length)
        count = len(columns["action"])
        for index in range(count):
            place = f"trajectory {index // length}, step {index % length}" if length else f"record {index}"
            where = f"{dataset} (shard {name}, {place})"
            levels.append(level_from_document(_document(columns, index, sizes), sizes, source=where).level)
        parts["action"].append(columns["action"])
        parts["action_mask"].append(columns["action_mask"].astype(bool))
        parts["mask"].append(columns["mask"].astype(bool) if "mask" in columns else np.ones(count, bool))
        parts["done"].append(columns["done"].astype(bool) if length else np.zeros(count, bool))
        parts["timestep"].append(columns[f"{_STATE}timestep"].astype(np.int32))
    if len(lengths) > 1:
        raise LevelFileError(dataset, "shards mix trajectory and flat records, or trajectories of different lengths")
    if not levels:
        raise LevelFileError(dataset, "every shard is empty (no records)")
    length = lengths.pop()
    joined = {key: np.concatenate(value) for key, value in parts.items()}
    # Stacked on the host: stacking device arrays compiles a concatenation for every dataset length.
    stacked = jax.tree.map(lambda *leaves: jnp.asarray(np.stack([np.asarray(x) for x in leaves])), *levels)
    return KinetixTransitions(
        levels=stacked,
        action=joined["action"],
        action_mask=joined["action_mask"],
        mask=joined["mask"],
        done=joined["done"] if length else None,
        timestep=joined["timestep"],
        trajectory_length=length,
    )


# ---------------------------------------------------------------------------------------------------------------
# Observations


ObserveFn = Callable[[SimState, Level, jax.Array], Any]
"""An observation function of (simulation state, level, agent step), e.g. `functools.partial(
impulse.engine.env.observations.observe, spec)`, for any observation type."""


@functools.cache
def _observe_batch(observe: ObserveFn) -> Callable[[Level, jax.Array], Any]:
    return jax.jit(jax.vmap(lambda level, timestep: observe(level.state, level, timestep)))


def kinetix_offline_observations(transitions: KinetixTransitions, observe: ObserveFn) -> Any:
    """Our observation of every transition's state ([N, ...] leaves), at its stored agent step: what a policy
    trained on the data would have seen. Pass the same `observe` object to reuse its compiled batch function."""
    return _observe_batch(observe)(transitions.levels, jnp.asarray(transitions.timestep))
