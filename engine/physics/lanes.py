"""Scenes on lanes: the data layout of the Pallas solver kernel (solver_kernel.py).

The XLA step keeps one scene's values in arrays with a slot axis and vmaps over scenes. A GPU kernel wants the
opposite: each lane of a block holds one scene, and every body, joint and contact slot is a row that the kernel
names at trace time (a static row load or store, never a gather). `RowLayout` is the one place that knows which row
is which: it packs named per-scene fields into one [rows, scenes] array and hands the kernel each field back as a
list of rows.

A field of shape [S, n] takes n rows; a field of 2D vectors [S, n, 2] takes 2n rows, x and y of vector i at rows
2i and 2i + 1 (`vectors` pairs them again). The row count is padded to a power of two, as Triton's block shapes
must be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp

Array = jax.Array
Row = Array  # [lanes] one value per scene of the block
Vector = tuple[Row, Row]


@dataclass(frozen=True)
class RowLayout:
    """Named blocks of consecutive rows: `fields` is ((name, num_rows), ...) in row order."""

    fields: tuple[tuple[str, int], ...]

    @property
    def offsets(self) -> dict[str, int]:
        starts, row = {}, 0
        for name, count in self.fields:
            starts[name] = row
            row += count
        return starts

    @property
    def num_rows(self) -> int:
        """Rows of the packed array: the fields' rows padded to a power of two (at least 8)."""
        used = sum(count for _, count in self.fields)
        return max(8, 1 << math.ceil(math.log2(max(used, 1))))

    def pack(self, values: dict[str, Array]) -> Array:
        """[scenes, ...] per field -> one [num_rows, scenes] float32 array (scenes on the minor axis)."""
        scenes = next(iter(values.values())).shape[0]
        columns = []
        for name, count in self.fields:
            field = jnp.asarray(values[name], dtype=jnp.float32).reshape(scenes, -1)
            if field.shape[1] != count:
                raise ValueError(f"field {name!r} has {field.shape[1]} values per scene, the layout says {count}")
            columns.append(field)
        used = sum(count for _, count in self.fields)
        columns.append(jnp.zeros((scenes, self.num_rows - used), jnp.float32))
        return jnp.concatenate(columns, axis=1).T

    def unpack(self, packed: Array) -> dict[str, Array]:
        """The inverse of `pack`: [num_rows, scenes] -> {name: [scenes, num_rows_of_field]}."""
        starts = self.offsets
        return {name: packed[starts[name] : starts[name] + count].T for name, count in self.fields}

    def load(self, ref) -> dict[str, list[Row]]:
        """Inside a kernel: every field as a list of rows, each a [lanes] value read from the block `ref`."""
        starts = self.offsets
        return {name: [ref[starts[name] + i, :] for i in range(count)] for name, count in self.fields}

    def row(self, ref, name: str, index: int) -> Row:
        """Inside a kernel: row `index` of field `name`, read from the block `ref` where it is used."""
        return ref[self.offsets[name] + index, :]

    def store(self, ref, rows: dict[str, list[Row]]) -> None:
        """Inside a kernel: write every field's rows into the block `ref` (rows past the fields are zeroed)."""
        starts = self.offsets
        for name, count in self.fields:
            for i in range(count):
                ref[starts[name] + i, :] = rows[name][i]
        used = sum(count for _, count in self.fields)
        if used < self.num_rows:
            zero = jnp.zeros_like(rows[self.fields[0][0]][0])
            for r in range(used, self.num_rows):
                ref[r, :] = zero


def vectors(rows: list[Row]) -> list[Vector]:
    """Rows of a vector field (x0, y0, x1, y1, ...) as (x, y) pairs."""
    return [(rows[2 * i], rows[2 * i + 1]) for i in range(len(rows) // 2)]


def flatten(vecs: list[Vector]) -> list[Row]:
    """The inverse of `vectors`."""
    return [component for vector in vecs for component in vector]
