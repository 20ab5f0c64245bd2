"""How the actor-learner types travel on the bus: pytrees as flat named arrays, and the schemas that check them.

This is the one place that knows the wire layout of a `TrajectoryBatch` and of the policy weights. A pytree
becomes `{name: array}` with names made from its paths (`steps/obs/polygons`, `params/actor/dense_0/kernel`; see
`engine.pytree.tree_arrays`), and is rebuilt in the order of a template of the same structure, which both
ends derive from the same config. Receivers check every message against a schema made from that template (exact
shapes, dtypes and finiteness) before it reaches a jitted function, so a foreign or corrupt message is refused
at the door instead of crashing or recompiling one.

**Two trajectory formats** (`TrajectoryWire`, the frame's `bus.trajectories` format number). `padded` (format 1,
the default) sends the batch's arrays as they are: no work beyond one copy into the frame, which is what a run on
one machine wants, where bytes cost little (shared memory) and the actors' and the learner's time is the limit.
`compact` (format 2, `bus.wire_compact`) is for runs across hosts, where the network is the limit. A batch pads
every entity to the size's slot counts and is mostly observation, so compact frames carry:

- booleans (masks, done flags, the attention mask) travel as bits (`np.packbits`, C order, `name` as uint8);
- the entity rows (`polygons`, `circles`, `joints`, `thrusters`, `joint_indexes`, `thruster_indexes`) and the
  rows of the symbolic vector (`engine.env.observations.symbolic_rows`) travel only where they differ, bit for bit,
  from a fill row: `name` holds the differing rows (slot by slot, in instance order, flattened), `name:rows` one bit
  per (instance, row) saying which rows those are, `name:fill` one instance whose rows stand in for all the others.
  The fill is the row of an inactive entity (the first inactive one the obs mask shows; zeros for the symbolic
  vector, whose inactive rows are zero), so in practice only active rows travel; but any row that differs from the
  fill is sent, so the learner rebuilds exactly the padded arrays its update was compiled for, whatever the levels
  put in their unused slots;
- with `float16` (`bus.wire_float16`), observation features travel as float16 when every value of the array
  fits float16's range (else float32), and are widened back to float32 by the learner: a rounding of the inputs
  (relative error <= 2^-11), not of the layout.

Sending a compact frame costs one pass over each array into the frame (`bus.codec.Deferred`: rows are cut and
converted while copied), plus reads to find the differing rows and small temporaries (the bits); the learner's
`unpack` allocates the full arrays once (decoding a padded frame copies nothing). Both cost several times the
padded copy (benchmarks/RESULTS.md, "The compact trajectory format").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from impulse.actors.trajectory import Trajectory, TrajectoryBatch, make_batch
from impulse.bus.codec import Deferred, Kind, Message, Rejected, tree_hash
from impulse.bus.schema import ArraySpec, Schema, check
from impulse.engine.env.actions import action_space
from impulse.engine.env.observations import observation_shape, symbolic_length, symbolic_rows
from impulse.engine.env.spec import EnvSpec
from impulse.engine.levels.level import LEVEL_ID_WORDS
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.pytree import path_name, tree_from_arrays

TRAJECTORY_FINITE = ("steps/obs", "steps/log_prob", "steps/value", "steps/reward", "steps/episode_return",
                     "bootstrap_obs")
"""Float arrays of a trajectory that must hold no NaN or Inf (a NaN reward would poison the update)."""


def trajectory_template(spec: EnvSpec, num_envs: int, num_steps: int) -> TrajectoryBatch:
    """The shapes and dtypes (`jax.ShapeDtypeStruct` leaves) of the batch an actor of `num_envs` environments of
    `spec` sends after `num_steps` steps: what the learner's update is compiled for and what every receiver checks
    frames against. Written out from the observation's and the action's shapes rather than traced through a
    rollout (which costs seconds in every process that needs it); the per-batch fields come from `make_batch`
    itself. tests/actors/test_wire.py checks it against a traced rollout for each observation and action kind."""
    shape = jax.ShapeDtypeStruct
    one_obs = observation_shape(spec)
    bootstrap_obs = jax.tree.map(lambda leaf: shape((num_envs, *leaf.shape), leaf.dtype), one_obs)
    action = action_space(spec)

    def per_step(dtype: Any, *tail: int) -> jax.ShapeDtypeStruct:
        return shape((num_steps, num_envs, *tail), dtype)

    steps = Trajectory(
        obs=jax.tree.map(lambda leaf: per_step(leaf.dtype, *leaf.shape), one_obs),
        action=per_step(jnp.dtype(action.dtype), *action.shape),
        log_prob=per_step(jnp.float32), value=per_step(jnp.float32), reward=per_step(jnp.float32),
        done=per_step(jnp.bool_), solved=per_step(jnp.bool_), truncated=per_step(jnp.bool_),
        episode_return=per_step(jnp.float32), level_id=per_step(jnp.uint32, LEVEL_ID_WORDS),
    )
    return jax.eval_shape(make_batch, steps, bootstrap_obs, 0)


def _specs(template: Any, finite: tuple[str, ...] | bool) -> dict[str, ArraySpec]:
    specs = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(template)[0]:
        name = path_name(path)
        is_finite = finite if isinstance(finite, bool) else any(name == f or name.startswith(f + "/") for f in finite)
        specs[name] = ArraySpec(np.dtype(leaf.dtype), tuple(leaf.shape), is_finite)
    return specs


def trajectory_schema(template: TrajectoryBatch) -> Schema:
    """Exactly the batch shapes the learner's update was compiled for."""
    return Schema(Kind.TRAJECTORY, _specs(template, TRAJECTORY_FINITE))


def weights_hash(params: Any) -> str:
    """Names, dtypes and shapes of the parameters: an actor refuses weights of another network by it."""
    return tree_hash({name: _shape_only(leaf) for name, leaf in _named_leaves(params)})


def _named_leaves(tree: Any) -> list[tuple[str, Any]]:
    return [(path_name(path), leaf) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]]


def _shape_only(leaf: Any) -> np.ndarray:
    """A zero-stride array with the leaf's dtype and shape: `tree_hash` reads only those."""
    return np.lib.stride_tricks.as_strided(np.zeros((), leaf.dtype), shape=leaf.shape, strides=(0,) * len(leaf.shape))


def weights_schema(params_template: Any) -> Schema:
    """The weights of this network: exact shapes, finite values, matching tree hash."""
    return Schema(Kind.WEIGHTS, _specs(params_template, True), tree_hash=weights_hash(params_template))


def checked_tree(message: Message, schema: Schema, template: Any) -> Any:
    """The pytree a message carries, after checking it against `schema` (raises `bus.codec.Rejected` if not)."""
    check(message, schema)
    return tree_from_arrays(message.arrays, template)



# -- the compact trajectory format -----------------------------------------------------------------------------

ROWS = ":rows"
"""Suffix of the bits saying which rows of a row-cut array travel."""
FILL = ":fill"
"""Suffix of the one instance whose rows stand in for the rows that do not travel."""
ENTITY_ROWS = {"polygons": "polygon_mask", "circles": "circle_mask", "joints": "joint_mask",
               "thrusters": "thruster_mask", "joint_indexes": "joint_mask", "thruster_indexes": "thruster_mask"}
"""Entity observation arrays cut by rows, and the mask whose inactive slots give their fill rows."""
HALF = frozenset({"polygons", "circles", "joints", "thrusters"})
"""Entity feature arrays that may travel as float16 (the symbolic vector may too)."""
FLOAT16_MAX = float(np.finfo(np.float16).max)
_CHUNK = 4096  # instances compared at a time (bounds the comparison's temporary)


@dataclass(frozen=True)
class _Field:
    """How one array of the batch travels: as bits, by rows, or as it is."""

    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    lead: int = 0  # leading dimensions that count instances (T, E for steps; E for the bootstrap observation)
    blocks: tuple[tuple[int, int], ...] = ()  # (rows, features per row) over one flattened instance; () uncut
    mask: str | None = None  # the entity mask choosing the fill rows (None: zeros)
    half: bool = False  # may travel as float16

    @property
    def instances(self) -> int:
        return math.prod(self.shape[:self.lead])

    @property
    def instance(self) -> int:
        return math.prod(self.shape[self.lead:])

    @property
    def rows(self) -> int:
        return sum(rows for rows, _ in self.blocks)


def _field(name: str, dtype: np.dtype, shape: tuple[int, ...], sizes: SceneSizes | None) -> _Field:
    if dtype == np.bool_:
        return _Field(name, dtype, shape)
    parts = name.split("/")
    if parts[0] == "steps" and len(parts) > 1 and parts[1] == "obs":
        lead, prefix = 2, "steps/obs"
    elif parts[0] == "bootstrap_obs":
        lead, prefix = 1, "bootstrap_obs"
    else:
        return _Field(name, dtype, shape)
    if name != prefix and parts[-1] in ENTITY_ROWS and len(shape) > lead:
        return _Field(name, dtype, shape, lead, ((shape[lead], math.prod(shape[lead + 1:])),),
                      f"{prefix}/{ENTITY_ROWS[parts[-1]]}", parts[-1] in HALF and dtype == np.float32)
    if (name == prefix and dtype == np.float32 and sizes is not None and len(shape) == lead + 1
            and shape[-1] == symbolic_length(sizes)):
        return _Field(name, dtype, shape, lead, symbolic_rows(sizes), None, True)
    return _Field(name, dtype, shape)


def _need(arrays: Mapping[str, np.ndarray], name: str, dtypes: tuple[np.dtype, ...], shape: tuple[int, ...] | None,
          ) -> np.ndarray:
    array = arrays.get(name)
    if array is None:
        raise Rejected("schema", f"array {name!r} is missing")
    if array.dtype not in dtypes:
        raise Rejected("bad_dtype", f"array {name!r} has dtype {array.dtype}, expected {' or '.join(map(str, dtypes))}")
    if shape is not None and array.shape != shape:
        raise Rejected("bad_shape", f"array {name!r} has shape {array.shape}, expected {shape}")
    return array


def _bits_shape(count: int) -> tuple[int]:
    return (-(-count // 8),)


PADDED_FORMAT = 1
"""Frame format of the arrays as they are."""
COMPACT_FORMAT = 2
"""Frame format of the compact layout."""


class TrajectoryWire:
    """The trajectory format of one batch shape (see the module docstring): `pack` on the actor, `checked` (or
    `unpack`) on the learner. Both ends build it from the same template and settings; `sizes` names the scene
    sizes, which the compact symbolic vector's rows need (without them it travels uncut). `float16` needs
    `compact`."""

    def __init__(self, template: TrajectoryBatch, sizes: SceneSizes | None = None, *, compact: bool = False,
                 float16: bool = False):
        if float16 and not compact:
            raise ValueError("float16 features are part of the compact format: set compact as well")
        self.template = template
        self.schema = trajectory_schema(template)
        self.compact = compact
        self.float16 = float16
        self.format = COMPACT_FORMAT if compact else PADDED_FORMAT
        """The frame format number (`bus.trajectories`): a frame of another is refused as "bad_version"."""
        self.fields = {name: _field(name, spec.dtype, tuple(int(d) for d in spec.shape), sizes)
                       for name, spec in self.schema.arrays.items()} if compact else {}
        self.max_frame_bytes = 2 * sum(spec.dtype.itemsize * math.prod(spec.shape)
                                       for spec in self.schema.arrays.values()) + (1 << 20)
        """The largest frame a receiver reads: twice the padded arrays, plus room for the header and table (a
        larger one is refused before it is parsed)."""

    # -- sending ------------------------------------------------------------------------------------------

    def pack(self, arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray | Deferred]:
        """The frame's arrays for a batch's `tree_arrays`; row-cut arrays are written into the frame by
        `bus.codec.encode` (no copy here)."""
        out: dict[str, np.ndarray | Deferred] = {}
        for name, value in arrays.items():
            field = self.fields.get(name)
            array = np.asarray(value)
            if not array.flags.c_contiguous:
                array = np.ascontiguousarray(array)  # never 0-d: only when needed
            if field is None:
                out[name] = array
                continue
            if array.shape != field.shape or array.dtype != field.dtype:
                raise ValueError(f"array {name!r} is {array.dtype}{list(array.shape)}, this wire's template says "
                                 f"{field.dtype}{list(field.shape)}")
            if field.dtype == np.bool_:
                out[name] = np.packbits(array.reshape(-1))
            elif field.blocks:
                self._pack_rows(field, array, arrays, out)
            else:
                out[name] = array
        return out

    def _fill(self, field: _Field, flat: np.ndarray, arrays: Mapping[str, np.ndarray]) -> np.ndarray:
        if field.mask is None:
            return np.zeros(field.instance, field.dtype)
        slots = field.blocks[0][0]
        mask = np.asarray(arrays[field.mask]).reshape(field.instances, slots)
        first_inactive = np.argmax(~mask, axis=0)  # 0 where a slot is never inactive: any row does, exactly
        return flat.reshape(field.instances, slots, -1)[first_inactive, np.arange(slots)].reshape(-1)

    def _pack_rows(self, field: _Field, array: np.ndarray, arrays: Mapping[str, np.ndarray],
                   out: dict[str, np.ndarray | Deferred]) -> None:
        n = field.instances
        flat = array.reshape(n, field.instance)
        fill = self._fill(field, flat, arrays)
        unsigned = np.dtype(f"<u{field.dtype.itemsize}")  # compare bits: -0.0 is not 0.0 here
        bits, fill_bits = flat.view(unsigned), fill.view(unsigned)
        keeps, start, total = [], 0, 0
        for rows, width in field.blocks:
            block = bits[:, start:start + rows * width].reshape(n, rows, width)
            block_fill = fill_bits[start:start + rows * width].reshape(rows, width)
            keep = np.empty((n, rows), bool)
            for at in range(0, n, _CHUNK):
                np.any(block[at:at + _CHUNK] != block_fill, axis=-1, out=keep[at:at + _CHUNK])
            keeps.append(keep)
            total += int(keep.sum()) * width
            start += rows * width
        dtype = field.dtype
        if field.half and self.float16 and array.size and np.max(array) <= FLOAT16_MAX \
                and np.min(array) >= -FLOAT16_MAX:
            dtype = np.dtype(np.float16)

        def write(target: np.ndarray) -> None:
            at, start = 0, 0
            for (rows, width), keep in zip(field.blocks, keeps, strict=True):
                for row in range(rows):
                    chosen = keep[:, row]
                    count = int(chosen.sum()) * width
                    columns = flat[:, start + row * width:start + (row + 1) * width]
                    np.compress(chosen, columns, axis=0, out=target[at:at + count].reshape(-1, width))
                    at += count
                start += rows * width

        out[field.name] = Deferred((total,), dtype, write)
        out[field.name + ROWS] = np.packbits(np.concatenate([keep.reshape(-1) for keep in keeps]))
        out[field.name + FILL] = fill

    # -- receiving ----------------------------------------------------------------------------------------

    def unpack(self, message: Message) -> dict[str, np.ndarray]:
        """The batch's arrays at the template's full shapes, rebuilt from a compact frame (a padded one's as they
        are); raises `Rejected` for anything that does not fit this format (the schema check follows in
        `checked`)."""
        arrays = message.arrays
        if not self.compact:
            return dict(arrays)
        out: dict[str, np.ndarray] = {}
        for name, field in self.fields.items():
            if field.dtype == np.bool_:
                count = math.prod(field.shape)
                packed = _need(arrays, name, (np.dtype(np.uint8),), _bits_shape(count))
                out[name] = np.unpackbits(packed, count=count).view(np.bool_).reshape(field.shape)
            elif field.blocks:
                out[name] = self._unpack_rows(field, arrays)
            elif name in arrays:
                out[name] = arrays[name]
        return out

    def _unpack_rows(self, field: _Field, arrays: Mapping[str, np.ndarray]) -> np.ndarray:
        n, name = field.instances, field.name
        allowed = (field.dtype, np.dtype(np.float16)) if field.half else (field.dtype,)
        data = _need(arrays, name, allowed, None)
        if data.ndim != 1:
            raise Rejected("bad_shape", f"array {name!r} has shape {data.shape}, expected one dimension")
        packed = _need(arrays, name + ROWS, (np.dtype(np.uint8),), _bits_shape(n * field.rows))
        fill = _need(arrays, name + FILL, (field.dtype,), (field.instance,))
        keep_all = np.unpackbits(packed, count=n * field.rows).view(np.bool_)
        kept, at, expected = [], 0, 0
        for rows, width in field.blocks:
            # The rows a block sent, in the order `pack` wrote them: row by row, instances ascending in each.
            row_index, instance_index = np.nonzero(keep_all[at:at + n * rows].reshape(n, rows).T)
            kept.append((row_index, instance_index))
            expected += row_index.size * width
            at += n * rows
        if data.size != expected:
            raise Rejected("bad_shape", f"array {name!r} holds {data.size} values, its rows bits select {expected}")
        full = np.empty((n, field.instance), field.dtype)
        full[...] = fill
        at, start = 0, 0
        for (rows, width), (row_index, instance_index) in zip(field.blocks, kept, strict=True):
            count = row_index.size * width
            if count:  # one scatter per block, into a (instance, row, feature) view of its columns
                block = np.lib.stride_tricks.as_strided(full[:, start:], shape=(n, rows, width),
                                                        strides=(full.strides[0], width * full.itemsize,
                                                                 full.itemsize))
                block[instance_index, row_index] = data[at:at + count].reshape(-1, width)
            at += count
            start += rows * width
        return full.reshape(field.shape)

    def checked(self, message: Message) -> TrajectoryBatch:
        """The batch a frame of this format carries, rebuilt and checked against the schema (raises `Rejected`)."""
        full = dataclasses.replace(message, arrays=self.unpack(message))
        return checked_tree(full, self.schema, self.template)
