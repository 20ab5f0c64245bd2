"""Scenes on lanes: the data layout of the Pallas solver kernel (solver_kernel.py).

The XLA step keeps one scene's values in arrays with a slot axis and vmaps over scenes. A GPU kernel wants the
opposite: each lane of a block holds one scene (one GPU thread per lane), and every body, joint and contact slot is
a row of the block. `RowLayout` is the one place that knows which row is which: it packs named per-scene fields into
one [rows, scenes] array, and inside the kernel it reads and writes a field's row `index` of a block ref, where
`index` may be a loop counter (a load or store at a computed row offset, the same for every lane) or, per lane, a
scene's own slot (`lane_row`: each lane reads its own row, a gather; how a joint reaches its bodies, which are
scene data).

A field of n values per scene takes n rows; a field of n 2D vectors takes 2n rows, the n x components and then the
n y components, so vector i is rows i and n + i of the field (a loop index added to two static offsets). The row
count is padded to a power of two, as Triton's block shapes must be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.physics.geometry import VectorOps

Array = jax.Array
Row = Array  # [lanes] one value per scene of the block
Vector = tuple[Row, Row]
Index = int | Array  # a row index: static, or a traced int32 scalar (a loop counter)


def add(a: Vector, b: Vector) -> Vector:
    return a[0] + b[0], a[1] + b[1]


def sub(a: Vector, b: Vector) -> Vector:
    return a[0] - b[0], a[1] - b[1]


def scale(s: Row, v: Vector) -> Vector:
    return s * v[0], s * v[1]


def dot(a: Vector, b: Vector) -> Row:
    return a[0] * b[0] + a[1] * b[1]


def cross(a: Vector, b: Vector) -> Row:
    return a[0] * b[1] - a[1] * b[0]


def spin_velocity(spin: Row, lever: Vector) -> Vector:
    """spin x lever: the velocity of a point at `lever` on a body spinning at `spin`."""
    return -spin * lever[1], spin * lever[0]


def nonzero(x: Row) -> Row:
    """`geometry.nonzero` on a row: x, or 1 where x == 0."""
    return jnp.where(x == 0, 1.0, x)


LANES = VectorOps(add=add, sub=sub, scale=scale, dot=dot, cross=cross, spin=spin_velocity)
"""`geometry.VectorOps` on lanes: a vector is a pair of rows (x, y), one value per scene each."""


class Field(NamedTuple):
    """A named field of a layout: `count` values (width 1) or 2D vectors (width 2) per scene."""

    name: str
    count: int
    width: int = 1


@dataclass(frozen=True)
class RowLayout:
    """Named blocks of consecutive rows, in row order."""

    fields: tuple[Field, ...]

    @property
    def offsets(self) -> dict[str, int]:
        """The first row of every field."""
        starts, row = {}, 0
        for field in self.fields:
            starts[field.name] = row
            row += field.count * field.width
        return starts

    @property
    def used_rows(self) -> int:
        return sum(field.count * field.width for field in self.fields)

    @property
    def num_rows(self) -> int:
        """Rows of the packed array: the fields' rows padded to a power of two (at least 8)."""
        return max(8, 1 << math.ceil(math.log2(max(self.used_rows, 1))))

    def pack(self, values: dict[str, Array]) -> Array:
        """[scenes, count] or [scenes, count, 2] per field -> one [num_rows, scenes] float32 array (scenes on the
        minor axis; a vector field's x components, then its y components)."""
        scenes = next(iter(values.values())).shape[0]
        columns = []
        for name, count, width in self.fields:
            field = jnp.asarray(values[name], dtype=jnp.float32)
            if field.size != scenes * count * width:
                raise ValueError(f"field {name!r} has {field.size // max(scenes, 1)} values per scene, the layout "
                                 f"says {count * width}")
            columns.append(field.reshape(scenes, count, width).transpose(0, 2, 1).reshape(scenes, count * width))
        columns.append(jnp.zeros((scenes, self.num_rows - self.used_rows), jnp.float32))
        return jnp.concatenate(columns, axis=1).T

    def unpack(self, packed: Array) -> dict[str, Array]:
        """The inverse of `pack`: [num_rows, scenes] -> {name: [scenes, count] or [scenes, count, 2]}."""
        starts, unpacked = self.offsets, {}
        for name, count, width in self.fields:
            rows = packed[starts[name] : starts[name] + count * width].T
            unpacked[name] = rows if width == 1 else rows.reshape(-1, width, count).transpose(0, 2, 1)
        return unpacked

    def count(self, name: str) -> int:
        """Values (or vectors) per scene of field `name`."""
        return next(field.count for field in self.fields if field.name == name)

    def index(self, name: str, index: Index, component: int = 0) -> Index:
        """The row of value `index` of field `name` (of a vector field: of its x or, component 1, y component);
        static, or the same traced int32 as `index` plus one static offset."""
        return self.offsets[name] + component * self.count(name) + index

    def row(self, ref, name: str, index: Index, component: int = 0) -> Row:
        """Inside a kernel: row `index` of field `name` on every lane of the block `ref`."""
        return ref[self.index(name, index, component), :]

    def set_row(self, ref, name: str, index: Index, value: Row, component: int = 0) -> None:
        """Inside a kernel: write row `index` of field `name` on every lane."""
        ref[self.index(name, index, component), :] = value

    def vector(self, ref, name: str, index: Index) -> Vector:
        """Inside a kernel: vector `index` of a vector field, (x, y), on every lane."""
        return self.row(ref, name, index), self.row(ref, name, index, component=1)

    def set_vector(self, ref, name: str, index: Index, value: Vector) -> None:
        self.set_row(ref, name, index, value[0])
        self.set_row(ref, name, index, value[1], component=1)

    def lane_row(self, ref, name: str, index: Array, lanes: Array, component: int = 0) -> Row:
        """Inside a kernel: on each lane, row `index[lane]` of field `name` (a gather). `index` is per-lane int32,
        `lanes` the lane numbers 0, 1, ... (`lane_numbers`)."""
        return ref[self.index(name, index, component), lanes]

    def set_lane_row(self, ref, name: str, index: Array, lanes: Array, value: Row, component: int = 0) -> None:
        """Inside a kernel: on each lane, write `value[lane]` to row `index[lane]` of field `name` (a scatter)."""
        ref[self.index(name, index, component), lanes] = value

    def lane_vector(self, ref, name: str, index: Array, lanes: Array) -> Vector:
        """Inside a kernel: on each lane, vector `index[lane]` of a vector field."""
        return self.lane_row(ref, name, index, lanes), self.lane_row(ref, name, index, lanes, component=1)

    def set_lane_vector(self, ref, name: str, index: Array, lanes: Array, value: Vector) -> None:
        self.set_lane_row(ref, name, index, lanes, value[0])
        self.set_lane_row(ref, name, index, lanes, value[1], component=1)

    def entry(self, ref, name: str, index: Index) -> Array:
        """Inside a kernel: entry `index` of field `name` of a 1D table `ref` shared by all lanes (a scalar)."""
        return ref[self.index(name, index)]


def lane_numbers(lanes: int) -> Array:
    """Inside a kernel: 0, 1, ..., lanes - 1, the column of each lane of a block (beside per-lane row indices)."""
    return jax.lax.broadcasted_iota(jnp.int32, (lanes,), 0)
