"""The message frame: a fixed header, a JSON array table and the raw array bytes, decoded as zero-copy views.

Every message of the system (trajectories, weights, levels, results, credits, metrics, control) is one frame, so
one decoder validates everything that arrives from the network before any other code touches it. A frame is::

    offset  size  field            type   meaning
    0       4     magic            4s     b"IMPZ"
    4       2     schema_version   u16    SCHEMA_MAJOR of the sender
    6       2     kind             u16    a Kind
    8       4     flags            u32    bit 0 (FLAG_DIGEST): a digest trailer follows the body; other bits 0
    12      8     run_hash         u64    first 8 bytes of blake2b(run id): a message of another run is refused
    20      8     policy_version   u64    version of the policy that produced the data (or of the weights)
    28      4     learner_epoch    u32    how many times the learner has restarted (versions restart with it)
    32      8     seq              u64    per-sender sequence number (gaps = loss, repeats = replays)
    40      4     table_len        u32    length of the JSON table
    44      8     body_len         u64    length of the body
    52      ...   table            JSON   {"arrays": [[name, dtype, shape, offset, nbytes], ...], "meta": {...}};
                                           UTF-8, at most MAX_TABLE_BYTES
    ...     pad   zeros up to the next multiple of 64 bytes
    B       ...   body             the arrays' bytes, C order, little-endian, each starting at a multiple of 64
                                   bytes from B; an array's `offset` is relative to B

    B+body  32    digest           bytes  with FLAG_DIGEST only: BLAKE2b-256 of every byte before it

All integers are little-endian. The frame's total length is exactly B + body_len (+ DIGEST_SIZE with a digest).

A frame names no sender: who sent it is what the key it arrived on says (each role publishes only under its own
prefix, `bus.keys`), which a router with access control guarantees; a name inside a payload would prove nothing.

Control frames (`DIGESTED_KINDS`: weights, credits, level batches, status, control replies) carry a digest of the
whole frame, header and array bytes included, and `decode` refuses one without it or whose bytes do not match it
("digest"): a flipped bit anywhere in a weights frame is caught before the weights are adopted. A digest is not a
signature (anyone can compute one); who may publish is the router's business. Data frames (trajectories, level
results) carry none: hashing a 150 MB trajectory would cost more than the rest of its journey, and their arrays
are checked against the schema and for NaN/Inf on arrival.

Copies: `encode` copies each array once, into one fresh bytearray, and returns that bytearray, not `bytes(...)`
(zenoh copies either alike, so converting would only add a copy); `decode` copies nothing: the arrays are
read-only numpy views into the buffer it was given (docs/distributed.md has the measured times).

`decode` trusts nothing: every length is compared with the actual payload before anything is sliced, nothing
of a declared size is allocated, and every failure is a `Rejected` with a reason from REASONS.
"""

from __future__ import annotations

import enum
import hashlib
import json
import math
import reprlib
import struct
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, NamedTuple

import numpy as np

SCHEMA_MAJOR = 2
"""Major version of the wire format. Incompatible changes bump it, which changes every key (`v1` -> `v2`).
2: keys under each role's own prefix, no sender name in frames, digests on control frames. A change confined to
one message family's arrays versions that family instead, inside its frames (the trajectories' formats:
`bus.trajectories`), so that frames of another format still arrive and are refused and counted."""

MAGIC = b"IMPZ"
HEADER = struct.Struct("<4sHHIQQIQIQ")
"""Layout of the fixed header (see the module docstring)."""
HEADER_SIZE = HEADER.size
ALIGN = 64
"""Alignment of the body and of every array in it, in bytes."""
MAX_TABLE_BYTES = 1 << 20
"""Largest array table accepted: a table this big would describe tens of thousands of arrays."""
MAX_NDIM = 32
FLAG_DIGEST = 1
"""Header flag: the frame ends with a DIGEST_SIZE-byte BLAKE2b digest of everything before it."""
DIGEST_SIZE = 32
TREE_HASH_META = "tree_hash"
"""Meta key carrying `tree_hash` of the arrays (weights carry it so that an actor refuses a foreign network)."""

REASONS = (
    "truncated",
    "oversized",
    "bad_magic",
    "bad_version",
    "wrong_run",
    "wrong_kind",
    "bad_table",
    "bad_dtype",
    "bad_shape",
    "bad_size",
    "non_finite",
    "schema",
    "tree_hash",
    "stale",
    "duplicate",
    "digest",
    "foreign_learner",
)
"""Why a message was refused. `decode` uses the first ten and digest; `schema.check` adds non_finite, schema,
tree_hash (and bad_dtype, bad_shape); stale and duplicate are for consumers that track policy versions and
sequence numbers (an older version than one already held, a sequence number or version seen before);
foreign_learner is for weights from a learner instance other than the one a follower follows (`actors.follow`)."""

_U32_MAX = (1 << 32) - 1
_U64_MAX = (1 << 64) - 1
_MAX_ARRAY_BYTES = 1 << 62  # numpy refuses arrays whose nominal size does not fit in an intp
_BRIEF = reprlib.Repr()  # bounded repr of hostile JSON, for error details
_BRIEF.maxlevel, _BRIEF.maxlist, _BRIEF.maxdict, _BRIEF.maxstring, _BRIEF.maxother = 3, 8, 8, 40, 40

_WIRE_TYPES = (
    np.bool_,
    np.int8,
    np.int16,
    np.int32,
    np.int64,
    np.uint8,
    np.uint16,
    np.uint32,
    np.uint64,
    np.float16,
    np.float32,
    np.float64,
)
WIRE_DTYPES: Mapping[str, np.dtype] = {
    np.dtype(t).newbyteorder("<").str: np.dtype(t).newbyteorder("<") for t in _WIRE_TYPES
}
"""dtype strings allowed in a frame (little-endian, `|` for one-byte types) and their numpy dtypes."""


class Kind(enum.IntEnum):
    """What a frame carries; a receiver states which kinds it accepts on each key."""

    TRAJECTORY = 1
    WEIGHTS = 2
    CREDIT = 3
    LEVEL_RESULTS = 4
    LEVELS = 5
    METRICS = 6
    CONTROL = 7
    EVALUATION = 8


DIGESTED_KINDS = frozenset({Kind.WEIGHTS, Kind.CREDIT, Kind.LEVELS, Kind.METRICS, Kind.CONTROL, Kind.EVALUATION})
"""Kinds that travel with a digest of the whole frame (see the module docstring)."""


class Header(NamedTuple):
    """The fixed header fields, in wire order."""

    magic: bytes
    schema_version: int
    kind: int
    flags: int
    run_hash: int
    policy_version: int
    learner_epoch: int
    seq: int
    table_len: int
    body_len: int


class Rejected(Exception):
    """A message refused by `decode` or `schema.check`: `reason` is one of REASONS, `detail` says what was wrong."""

    def __init__(self, reason: str, detail: str) -> None:
        if reason not in REASONS:
            raise ValueError(f"unknown reject reason {reason!r}; expected one of {REASONS}")
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


class Deferred(NamedTuple):
    """An array `encode` does not copy but has written straight into its place in the frame: `write(out)` fills
    `out`, a writable [shape] view of `dtype` into the frame. A sender that cuts or converts an array on the way
    (`actors.wire`) does it in this one pass instead of building the result first and copying it again."""

    shape: tuple[int, ...]
    dtype: np.dtype
    write: Callable[[np.ndarray], None]


@dataclass(frozen=True)
class Message:
    """A decoded frame. `arrays` are read-only views into the received payload (keep it alive while used)."""

    kind: Kind
    policy_version: int
    learner_epoch: int
    seq: int
    meta: dict[str, Any]
    arrays: dict[str, np.ndarray]



@lru_cache(maxsize=64)
def run_hash(run: str) -> int:
    """The u64 a frame carries for its run: the first 8 bytes of blake2b(run id), little-endian."""
    return int.from_bytes(hashlib.blake2b(run.encode("utf-8")).digest()[:8], "little")


def wire_dtype(dtype: np.dtype | type | str) -> np.dtype:
    """The little-endian dtype an array of `dtype` travels as; ValueError for types the wire does not carry."""
    dt = np.dtype(dtype)
    wire = dt.newbyteorder("<") if dt.byteorder != "|" else dt
    if wire.str not in WIRE_DTYPES:
        raise ValueError(f"dtype {dt} cannot be sent; allowed: bool, (u)int8-64, float16/32/64")
    return WIRE_DTYPES[wire.str]


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def _check_range(name: str, value: int, limit: int) -> int:
    if not isinstance(value, int | np.integer) or not 0 <= int(value) <= limit:
        raise ValueError(f"{name} must be an integer in [0, {limit}], got {value!r}")
    return int(value)


def encode(
    kind: Kind,
    arrays: Mapping[str, np.ndarray],
    *,
    run: str,
    policy_version: int = 0,
    learner_epoch: int = 0,
    seq: int = 0,
    meta: Mapping[str, Any] | None = None,
) -> bytearray:
    """One frame holding `arrays` (a flat mapping; see `flatten`; a value may be a `Deferred`), ready to `put`;
    kinds of DIGESTED_KINDS end with the digest of the frame.

    Each array is copied exactly once, into the frame (non-contiguous or big-endian inputs are converted during
    that copy). Returns the bytearray itself: zenoh accepts it and copies it anyway, so `bytes()` would be waste.
    """
    kind = Kind(kind)
    policy_version = _check_range("policy_version", policy_version, _U64_MAX)
    learner_epoch = _check_range("learner_epoch", learner_epoch, _U32_MAX)
    seq = _check_range("seq", seq, _U64_MAX)
    entries: list[list[Any]] = []
    copies: list[tuple[np.ndarray | Deferred, np.dtype, int]] = []
    body_len = 0
    for name, value in arrays.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"array names must be non-empty strings, got {name!r}")
        array = value if isinstance(value, Deferred) else np.asarray(value)
        dtype = wire_dtype(array.dtype)
        offset = _aligned(body_len)
        nbytes = math.prod(array.shape) * dtype.itemsize
        entries.append([name, dtype.str, [int(d) for d in array.shape], offset, nbytes])
        copies.append((array, dtype, offset))
        body_len = offset + nbytes
    table = json.dumps({"arrays": entries, "meta": dict(meta or {})}, separators=(",", ":"))
    table_bytes = table.encode("utf-8")
    if len(table_bytes) > MAX_TABLE_BYTES:
        raise ValueError(f"array table of {len(table_bytes)} bytes exceeds {MAX_TABLE_BYTES}; send fewer arrays")
    body_start = _aligned(HEADER_SIZE + len(table_bytes))
    digested = kind in DIGESTED_KINDS
    frame = bytearray(body_start + body_len + (DIGEST_SIZE if digested else 0))
    header = Header(
        magic=MAGIC,
        schema_version=SCHEMA_MAJOR,
        kind=kind,
        flags=FLAG_DIGEST if digested else 0,
        run_hash=run_hash(run),
        policy_version=policy_version,
        learner_epoch=learner_epoch,
        seq=seq,
        table_len=len(table_bytes),
        body_len=body_len,
    )
    HEADER.pack_into(frame, 0, *header)
    frame[HEADER_SIZE : HEADER_SIZE + len(table_bytes)] = table_bytes
    for array, dtype, offset in copies:
        if math.prod(array.shape):
            out = np.ndarray(array.shape, dtype, buffer=frame, offset=body_start + offset)
            if isinstance(array, Deferred):
                array.write(out)
            else:
                out[...] = array
    if digested:
        end = body_start + body_len
        frame[end:] = _digest(memoryview(frame)[:end])
    return frame


def _digest(data: memoryview) -> bytes:
    return hashlib.blake2b(data, digest_size=DIGEST_SIZE).digest()


def _byte_view(data: bytes | bytearray | memoryview) -> memoryview:
    view = memoryview(data)
    if view.ndim != 1 or view.itemsize != 1:
        view = view.cast("B")
    return view


def _accepted_kinds(kinds: Kind | Collection[Kind] | None) -> frozenset[Kind] | None:
    if kinds is None:
        return None
    if isinstance(kinds, int):
        return frozenset({Kind(kinds)})
    return frozenset(Kind(k) for k in kinds)


def _is_count(value: object) -> bool:
    """A JSON non-negative integer (bools are ints in Python but not counts)."""
    return type(value) is int and value >= 0


def _parse_table(raw: bytes) -> tuple[list[Any], dict[str, Any]]:
    try:
        table = json.loads(raw.decode("utf-8"))
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise Rejected("bad_table", f"array table is not valid UTF-8 JSON ({exc.__class__.__name__})") from None
    if not isinstance(table, dict):
        raise Rejected("bad_table", f"array table is a JSON {type(table).__name__}, expected an object")
    entries = table.get("arrays")
    meta = table.get("meta", {})
    if not isinstance(entries, list):
        raise Rejected("bad_table", "array table has no 'arrays' list")
    if not isinstance(meta, dict):
        raise Rejected("bad_table", f"'meta' is a JSON {type(meta).__name__}, expected an object")
    return entries, meta


def _array_view(
    entry: object, buf: memoryview, body_start: int, body_len: int, seen: set[str]
) -> tuple[str, np.ndarray]:
    """Validate one table entry against the body and return its name and read-only view."""
    if not isinstance(entry, list) or len(entry) != 5:
        raise Rejected("bad_table", f"table entry {_BRIEF.repr(entry)} is not [name, dtype, shape, offset, nbytes]")
    name, dtype_str, shape, offset, nbytes = entry
    if not isinstance(name, str) or not name:
        raise Rejected("bad_table", f"array name {_BRIEF.repr(name)} is not a non-empty string")
    if name in seen:
        raise Rejected("bad_table", f"array {name!r} appears twice in the table")
    if not isinstance(dtype_str, str) or dtype_str not in WIRE_DTYPES:
        raise Rejected("bad_dtype", f"array {name!r} has dtype {_BRIEF.repr(dtype_str)}, not one the wire carries")
    dtype = WIRE_DTYPES[dtype_str]
    if not isinstance(shape, list) or len(shape) > MAX_NDIM or not all(_is_count(d) for d in shape):
        raise Rejected("bad_shape", f"array {name!r} has shape {_BRIEF.repr(shape)}, expected non-negative integers")
    if math.prod(d for d in shape if d) * dtype.itemsize > _MAX_ARRAY_BYTES:
        raise Rejected("bad_shape", f"array {name!r} has shape {tuple(shape)}, too large for any array")
    if not _is_count(offset) or not _is_count(nbytes):
        where = f"offset {_BRIEF.repr(offset)} and nbytes {_BRIEF.repr(nbytes)}"
        raise Rejected("bad_size", f"array {name!r} has {where}, expected non-negative integers")
    count = math.prod(shape)
    if nbytes != count * dtype.itemsize:
        needed = count * dtype.itemsize
        raise Rejected("bad_size", f"array {name!r} declares {nbytes} bytes, {tuple(shape)} of {dtype} is {needed}")
    if offset + nbytes > body_len:
        where = f"offset {offset} with {nbytes} bytes"  # no sum: it could exceed int-to-str's digit limit
        raise Rejected("bad_size", f"array {name!r} at {where} ends past the {body_len}-byte body")
    seen.add(name)
    view = np.frombuffer(buf, dtype=dtype, count=count, offset=body_start + offset).reshape(shape)
    view.flags.writeable = False
    return name, view


def decode(
    data: bytes | bytearray | memoryview,
    *,
    run: str,
    kinds: Kind | Collection[Kind] | None = None,
    max_bytes: int = 1 << 30,
) -> Message:
    """Validate a frame and return its Message, or raise `Rejected` (never anything else for any byte string).

    `kinds` limits the accepted kinds (a trajectory arriving on the weights key is refused); `max_bytes` bounds
    the frame. Nothing is allocated from a declared size: lengths are compared with `len(data)` first. A frame
    of DIGESTED_KINDS must carry its digest, and any digest carried must match the frame's bytes.
    """
    buf = _byte_view(data)
    size = len(buf)
    if size > max_bytes:
        raise Rejected("oversized", f"frame of {size} bytes exceeds the {max_bytes}-byte limit")
    if size < HEADER_SIZE:
        raise Rejected("truncated", f"frame of {size} bytes is shorter than the {HEADER_SIZE}-byte header")
    header = Header._make(HEADER.unpack_from(buf, 0))
    if header.magic != MAGIC:
        raise Rejected("bad_magic", f"frame starts with {header.magic!r}, expected {MAGIC!r}")
    if header.schema_version != SCHEMA_MAJOR:
        raise Rejected("bad_version", f"schema version {header.schema_version}, this build reads {SCHEMA_MAJOR}")
    if header.run_hash != run_hash(run):
        raise Rejected("wrong_run", f"run hash {header.run_hash:#018x} is not that of run {run!r}")
    try:
        kind = Kind(header.kind)
    except ValueError:
        raise Rejected("wrong_kind", f"unknown message kind {header.kind}") from None
    accepted = _accepted_kinds(kinds)
    if accepted is not None and kind not in accepted:
        names = ", ".join(sorted(k.name for k in accepted))
        raise Rejected("wrong_kind", f"a {kind.name} message where {names} is expected")
    if header.table_len > MAX_TABLE_BYTES:
        raise Rejected("bad_table", f"array table of {header.table_len} bytes exceeds {MAX_TABLE_BYTES}")
    body_start = _aligned(HEADER_SIZE + header.table_len)
    digested = bool(header.flags & FLAG_DIGEST)
    if kind in DIGESTED_KINDS and not digested:
        raise Rejected("digest", f"a {kind.name} frame without the digest every {kind.name} frame carries")
    end = body_start + header.body_len
    declared = end + (DIGEST_SIZE if digested else 0)
    if declared > size:
        raise Rejected("truncated", f"header declares a {declared}-byte frame, payload has {size} bytes")
    if declared < size:
        raise Rejected("bad_size", f"header declares a {declared}-byte frame, payload has {size} bytes")
    if digested and _digest(buf[:end]) != bytes(buf[end:]):
        raise Rejected("digest", f"the {kind.name} frame's bytes do not match its digest (corrupted or altered)")
    entries, meta = _parse_table(bytes(buf[HEADER_SIZE : HEADER_SIZE + header.table_len]))
    seen: set[str] = set()
    arrays = dict(_array_view(entry, buf, body_start, header.body_len, seen) for entry in entries)
    return Message(
        kind=kind,
        policy_version=header.policy_version,
        learner_epoch=header.learner_epoch,
        seq=header.seq,
        meta=meta,
        arrays=arrays,
    )


def flatten(tree: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Nested mappings to one flat dict whose names join the keys with "/"; leaves become numpy arrays.

    A frame carries flat names; this is how a parameter tree or a trajectory batch becomes one. Empty nested
    mappings vanish. Two paths that flatten to the same name (`{"a/b": x, "a": {"b": y}}`) are a ValueError.
    """
    flat: dict[str, np.ndarray] = {}

    def visit(node: Mapping[str, Any], prefix: str) -> None:
        for key, value in node.items():
            if not isinstance(key, str) or not key:
                raise ValueError(f"tree keys must be non-empty strings, got {key!r} under {prefix!r}")
            name = f"{prefix}/{key}" if prefix else key
            if isinstance(value, Mapping):
                visit(value, name)
            elif name in flat:
                raise ValueError(f"two leaves flatten to the name {name!r}")
            else:
                flat[name] = np.asarray(value)

    visit(tree, "")
    return flat


def unflatten(flat: Mapping[str, Any]) -> dict[str, Any]:
    """The nested dicts whose `flatten` is `flat` (names split at "/"); ValueError if a name is both a leaf and a
    subtree."""
    tree: dict[str, Any] = {}
    for name, value in flat.items():
        *parents, leaf = name.split("/")
        node = tree
        for part in parents:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ValueError(f"{name!r} needs {part!r} to be a subtree, but it is a leaf")
            node = child
        if leaf in node:
            raise ValueError(f"{name!r} is both a leaf and a subtree")
        node[leaf] = value
    return tree


def tree_hash(flat: Mapping[str, np.ndarray]) -> str:
    """Hex digest of the structure of `flat`: the sorted (name, wire dtype, shape) triples, values excluded.

    Two networks agree on it exactly when their parameters can be swapped, so an actor compares the hash a
    weights message carries (meta TREE_HASH_META) with its own. Works on anything with `.dtype` and `.shape`
    (numpy or device arrays) without reading the values.
    """
    triples = sorted((name, wire_dtype(leaf.dtype).str, [int(d) for d in leaf.shape]) for name, leaf in flat.items())
    return hashlib.blake2b(json.dumps(triples, separators=(",", ":")).encode("utf-8"), digest_size=16).hexdigest()
