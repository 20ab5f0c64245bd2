"""Content validation: does a decoded message hold the arrays, dtypes and shapes its receiver was built for?

`codec.decode` only proves that a frame is well formed. A well-formed trajectory from an actor with another
observation size, or weights of another network, would still crash a jitted function (or silently recompile it)
far from where it arrived; `check` refuses it at the door with a reason and a sentence naming the array.
Named dimensions ("T", "E") must agree across all arrays of one message, and can be pinned by the receiver.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass

import numpy as np

from impulse.bus.codec import TREE_HASH_META, Kind, Message, Rejected, flatten, wire_dtype


@dataclass(frozen=True)
class ArraySpec:
    """What one array must look like: dtype, shape (ints are fixed sizes, strs named dimensions), finiteness."""

    dtype: np.dtype
    shape: tuple[int | str, ...]
    finite: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "dtype", wire_dtype(self.dtype))
        object.__setattr__(self, "shape", tuple(self.shape))
        for dim in self.shape:
            if isinstance(dim, bool) or not isinstance(dim, int | str) or (isinstance(dim, int) and dim < 0):
                raise ValueError(f"shape entries must be non-negative ints or dimension names, got {dim!r}")

    def describe(self) -> str:
        """The expected shape as text, e.g. `(T, E, 4)`."""
        return "(" + ", ".join(str(dim) for dim in self.shape) + ("," if len(self.shape) == 1 else "") + ")"


@dataclass(frozen=True)
class Schema:
    """The arrays a message of `kind` must carry. Extra arrays are allowed (a newer minor version may add some).

    `tree_hash`, when set, must equal the message's meta TREE_HASH_META (weights of a different network).
    """

    kind: Kind
    arrays: Mapping[str, ArraySpec]
    tree_hash: str | None = None

    @classmethod
    def from_example(
        cls,
        kind: Kind,
        example: Mapping[str, object],
        leading: tuple[str, ...] = (),
        finite: Collection[str] | bool = (),
        tree_hash: str | None = None,
    ) -> Schema:
        """A schema whose specs copy the dtypes and shapes of `example` (flat or nested arrays).

        The first len(leading) dimensions of every array are replaced by the names in `leading` (e.g. ("T", "E")
        for a trajectory, so any rollout length and env count is accepted as long as all arrays agree).
        `finite` is True for all arrays, or the names that must hold no NaN/Inf; a name also covers the arrays
        under it ("obs" covers "obs/shapes").
        """
        flat = flatten(example)
        if not isinstance(finite, bool):
            unknown = [name for name in finite if not any(_covers(name, key) for key in flat)]
            if unknown:
                raise ValueError(f"finite names {unknown} match no array of the example")
        specs: dict[str, ArraySpec] = {}
        for name, array in flat.items():
            if array.ndim < len(leading):
                raise ValueError(f"array {name!r} has {array.ndim} dims, fewer than the leading dims {leading}")
            shape = (*leading, *array.shape[len(leading) :])
            is_finite = finite if isinstance(finite, bool) else any(_covers(f, name) for f in finite)
            specs[name] = ArraySpec(array.dtype, shape, is_finite)
        return cls(Kind(kind), specs, tree_hash)


def _covers(prefix: str, name: str) -> bool:
    return name == prefix or name.startswith(prefix + "/")


def check(message: Message, schema: Schema, dims: Mapping[str, int] | None = None) -> dict[str, int]:
    """Raise `Rejected` unless `message` fits `schema`; return the named dimensions bound by it.

    `dims` pins named dimensions in advance (an actor's E, say). Checks run cheapest first: kind, tree hash,
    presence, dtypes and shapes of every array, and only then the NaN/Inf scan of the finite arrays.
    """
    if message.kind != schema.kind:
        raise Rejected("wrong_kind", f"a {message.kind.name} message where {schema.kind.name} is expected")
    if schema.tree_hash is not None:
        got = message.meta.get(TREE_HASH_META)
        if got != schema.tree_hash:
            raise Rejected("tree_hash", f"tree hash {got!r} differs from this network's {schema.tree_hash!r}")
    bound: dict[str, int] = dict(dims or {})
    binder: dict[str, str] = {name: "the receiver" for name in bound}
    for name, spec in schema.arrays.items():
        array = message.arrays.get(name)
        if array is None:
            raise Rejected("schema", f"array {name!r} is missing")
        if array.dtype != spec.dtype:
            raise Rejected("bad_dtype", f"array {name!r} has dtype {array.dtype}, expected {spec.dtype}")
        if array.ndim != len(spec.shape):
            raise Rejected("bad_shape", f"array {name!r} has shape {array.shape}, expected {spec.describe()}")
        for size, dim in zip(array.shape, spec.shape, strict=True):
            if isinstance(dim, int):
                if size != dim:
                    raise Rejected("bad_shape", f"array {name!r} has shape {array.shape}, expected {spec.describe()}")
            elif dim not in bound:
                bound[dim] = size
                binder[dim] = f"array {name!r}"
            elif bound[dim] != size:
                raise Rejected(
                    "bad_shape",
                    f"array {name!r} has shape {array.shape}, expected {spec.describe()} with {dim}={bound[dim]} "
                    f"(set by {binder[dim]})",
                )
    for name, spec in schema.arrays.items():
        array = message.arrays[name]
        if spec.finite and array.dtype.kind == "f" and not np.isfinite(array).all():
            bad = int(array.size - np.count_nonzero(np.isfinite(array)))
            raise Rejected("non_finite", f"array {name!r} holds {bad} NaN/Inf values")
    return bound
