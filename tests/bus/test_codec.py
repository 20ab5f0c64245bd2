"""The message frame: round trips, every malformed case refused with its reason, and fuzzing."""

from __future__ import annotations

import json
import tracemalloc
from typing import Any

import numpy as np
import pytest

from impulse.bus.codec import (
    ALIGN,
    DIGEST_SIZE,
    DIGESTED_KINDS,
    FLAG_DIGEST,
    HEADER,
    HEADER_SIZE,
    MAX_TABLE_BYTES,
    REASONS,
    Header,
    Kind,
    Message,
    Rejected,
    decode,
    encode,
    flatten,
    tree_hash,
    unflatten,
)
from impulse.bus.keys import SCHEMA_MAJOR

RUN = "codec-run"


def sample_arrays() -> dict[str, np.ndarray]:
    """Arrays of every wire dtype, scalars, zero-size, non-contiguous and big-endian inputs."""
    rng = np.random.default_rng(0)
    return {
        "obs/shapes": rng.standard_normal((3, 4, 5)).astype(np.float32),
        "obs/scalar": np.float64(2.5),
        "f16": rng.standard_normal(7).astype(np.float16),
        "done": rng.random((2, 3)) > 0.5,
        "i8": np.arange(-4, 4, dtype=np.int8),
        "i16": np.arange(6, dtype=np.int16).reshape(2, 3),
        "i32": np.arange(6, dtype=np.int32)[::2],
        "i64": np.array([-(2**62), 2**62], dtype=np.int64),
        "u8": np.arange(5, dtype=np.uint8),
        "u16": np.arange(5, dtype=np.uint16),
        "u32": np.arange(5, dtype=np.uint32),
        "u64": np.array([2**64 - 1], dtype=np.uint64),
        "empty": np.zeros((0,), np.float32),
        "empty3d": np.zeros((3, 0, 2), np.int64),
        "bigendian": np.arange(6, dtype=">f8").reshape(3, 2),
        "transposed": np.arange(12, dtype=np.int32).reshape(3, 4).T,
    }


def valid_frame(**overrides: Any) -> bytearray:
    fields: dict[str, Any] = {"run": RUN, "policy_version": 7, "learner_epoch": 2, "seq": 11}
    fields.update(overrides)
    return encode(Kind.TRAJECTORY, {"obs": np.arange(12, dtype=np.float32).reshape(3, 4)}, **fields)


def split(frame: bytes | bytearray) -> tuple[Header, dict[str, Any], bytes]:
    header = Header._make(HEADER.unpack_from(frame, 0))
    table = json.loads(bytes(frame[HEADER_SIZE : HEADER_SIZE + header.table_len]))
    return header, table, bytes(frame[len(frame) - header.body_len :])


def rebuild(frame: bytes | bytearray, table: Any = None, raw_table: bytes | None = None, **header: Any) -> bytes:
    """`frame` with its table and/or header fields replaced; lengths follow unless given in `header`."""
    old, old_table, body = split(frame)
    table_bytes = raw_table if raw_table is not None else json.dumps(old_table if table is None else table).encode()
    fields = old._replace(table_len=len(table_bytes), body_len=len(body))._replace(**header)
    body_start = -(-(HEADER_SIZE + len(table_bytes)) // ALIGN) * ALIGN
    padding = bytes(body_start - HEADER_SIZE - len(table_bytes))
    return HEADER.pack(*fields) + table_bytes + padding + body


def refused(data: bytes | bytearray, reason: str, **kwargs: Any) -> Rejected:
    kwargs.setdefault("run", RUN)
    with pytest.raises(Rejected) as info:
        decode(data, **kwargs)
    assert info.value.reason == reason, info.value
    assert info.value.detail
    return info.value


def with_entry(**changes: Any) -> bytes:
    """The valid frame with its one table entry modified (name, dtype, shape, offset, nbytes by name)."""
    frame = valid_frame()
    _, table, _ = split(frame)
    entry = dict(zip(["name", "dtype", "shape", "offset", "nbytes"], table["arrays"][0], strict=True))
    entry.update(changes)
    table["arrays"] = [list(entry.values())]
    return rebuild(frame, table)


# ------------------------------------------------------------------------------------------------ round trip


@pytest.mark.parametrize("kind", list(Kind))
def test_round_trip_every_kind(kind: Kind) -> None:
    arrays = sample_arrays()
    meta = {"tree_hash": "abc", "nested": {"x": [1, 2.5, None]}, "text": "é"}
    frame = encode(
        kind, arrays, run=RUN, policy_version=2**63 + 5, learner_epoch=2**32 - 1, seq=2**40, meta=meta
    )
    for data in (frame, bytes(frame), memoryview(frame)):
        message = decode(data, run=RUN, kinds=kind)
        assert isinstance(message, Message)
        assert message.kind is kind
        assert (message.policy_version, message.learner_epoch, message.seq) == (2**63 + 5, 2**32 - 1, 2**40)
        assert message.meta == meta
        assert list(message.arrays) == list(arrays)
        for name, expected in arrays.items():
            got = message.arrays[name]
            assert got.shape == np.shape(expected), name
            assert got.dtype == np.dtype(expected.dtype).newbyteorder("<"), name
            np.testing.assert_array_equal(got, expected, err_msg=name)
            assert not got.flags.writeable, name


def test_decoded_arrays_are_aligned_views_into_the_payload() -> None:
    frame = encode(Kind.WEIGHTS, sample_arrays(), run=RUN)
    message = decode(frame, run=RUN)
    base = np.frombuffer(frame, np.uint8).ctypes.data
    for name, array in message.arrays.items():
        if array.size:
            assert (array.ctypes.data - base) % ALIGN == 0, name
    view = message.arrays["u8"]
    offset = view.ctypes.data - base
    frame[offset] = 200  # the view sees a change of the buffer: no copy was made
    assert view[0] == 200


def test_encode_refuses_what_the_wire_cannot_carry() -> None:
    with pytest.raises(ValueError, match="cannot be sent"):
        encode(Kind.METRICS, {"c": np.zeros(2, np.complex64)}, run=RUN)
    with pytest.raises(ValueError, match="cannot be sent"):
        encode(Kind.METRICS, {"o": np.array([object()])}, run=RUN)
    with pytest.raises(ValueError, match="non-empty"):
        encode(Kind.METRICS, {"": np.zeros(2)}, run=RUN)
    with pytest.raises(ValueError, match="policy_version"):
        encode(Kind.METRICS, {}, run=RUN, policy_version=-1)
    with pytest.raises(ValueError, match="learner_epoch"):
        encode(Kind.METRICS, {}, run=RUN, learner_epoch=2**32)
    with pytest.raises(ValueError, match="table"):
        encode(Kind.METRICS, {}, run=RUN, meta={"x": "y" * MAX_TABLE_BYTES})


def test_rejected_only_takes_known_reasons() -> None:
    assert len(set(REASONS)) == len(REASONS) == 17
    with pytest.raises(ValueError, match="unknown reject reason"):
        Rejected("because", "no")


# ---------------------------------------------------------------------------------------------- malformed


def test_truncated_at_several_points() -> None:
    frame = bytes(valid_frame())
    header, _, _ = split(frame)
    for cut in [0, 1, 10, HEADER_SIZE - 1, HEADER_SIZE, HEADER_SIZE + header.table_len // 2, len(frame) - 1]:
        refused(frame[:cut], "truncated")


def test_trailing_bytes_and_oversize() -> None:
    frame = bytes(valid_frame())
    refused(frame + b"\0", "bad_size")
    refused(frame, "oversized", max_bytes=len(frame) - 1)
    assert decode(frame, run=RUN, max_bytes=len(frame)).seq == 11


def test_header_fields_checked() -> None:
    frame = valid_frame()
    refused(b"XXXX" + bytes(frame[4:]), "bad_magic")
    refused(rebuild(frame, schema_version=SCHEMA_MAJOR + 1), "bad_version")
    refused(rebuild(frame, schema_version=0), "bad_version")
    refused(frame, "wrong_run", run="another-run")
    refused(rebuild(frame, kind=99), "wrong_kind")
    refused(rebuild(frame, kind=0), "wrong_kind")
    refused(frame, "wrong_kind", kinds=Kind.WEIGHTS)
    refused(frame, "wrong_kind", kinds=[Kind.WEIGHTS, Kind.LEVELS])
    assert decode(frame, run=RUN, kinds=[Kind.WEIGHTS, Kind.TRAJECTORY]).kind is Kind.TRAJECTORY
    assert decode(rebuild(frame, flags=4), run=RUN).seq == 11  # reserved flags are ignored
    refused(rebuild(frame, flags=1), "truncated")  # a digest flag with no digest after the body


def test_bad_tables() -> None:
    frame = valid_frame()
    refused(rebuild(frame, raw_table=b"{not json"), "bad_table")
    refused(rebuild(frame, raw_table=b'{"arrays": "\xff\xfe"}'), "bad_table")
    refused(rebuild(frame, raw_table=b"[" * 200_000 + b"]" * 200_000), "bad_table")
    refused(rebuild(frame, table=[1, 2]), "bad_table")
    refused(rebuild(frame, table={"meta": {}}), "bad_table")
    refused(rebuild(frame, table={"arrays": [], "meta": [1]}), "bad_table")
    refused(rebuild(frame, table={"arrays": [["obs", "<f4", [3, 4], 0]]}), "bad_table")
    refused(rebuild(frame, table={"arrays": [7]}), "bad_table")
    refused(with_entry(name=5), "bad_table")
    refused(with_entry(name=""), "bad_table")
    refused(rebuild(frame, table_len=MAX_TABLE_BYTES + 1), "bad_table")
    minimal = decode(rebuild(frame, table={"arrays": []}), run=RUN)  # meta is optional
    assert (minimal.meta, minimal.arrays) == ({}, {})


def test_entries_pointing_outside_the_body_or_misdeclared() -> None:
    header, _, _ = split(valid_frame())
    refused(with_entry(offset=header.body_len - 8), "bad_size")
    refused(with_entry(offset=2**70), "bad_size")
    refused(with_entry(offset=-64), "bad_size")
    refused(with_entry(nbytes=47), "bad_size")
    refused(with_entry(nbytes=4.5), "bad_size")
    refused(with_entry(shape=[2**40], nbytes=2**42), "bad_size")


def test_bad_dtypes() -> None:
    for dtype in ["<c8", ">f4", "|O", "<U4", "float32", "<V8", 4, None]:
        refused(with_entry(dtype=dtype), "bad_dtype")


def test_bad_shapes() -> None:
    for shape in [[-1, 4], [3.0, 4], [True, 4], "3x4", None, [1] * 33, [[3], 4]]:
        refused(with_entry(shape=shape), "bad_shape")
    refused(with_entry(shape=[0, 2**62], nbytes=0), "bad_shape")  # zero bytes, yet no array can have that shape


def test_duplicate_names() -> None:
    frame = valid_frame()
    _, table, _ = split(frame)
    table["arrays"] = table["arrays"] * 2
    assert "twice" in refused(rebuild(frame, table), "bad_table").detail


def test_huge_declared_sizes_allocate_nothing() -> None:
    frame = valid_frame()
    tracemalloc.start()
    try:
        refused(rebuild(frame, body_len=2**63), "truncated")
        refused(rebuild(frame, table_len=2**32 - 1), "bad_table")
        refused(with_entry(shape=[2**30, 2**30], nbytes=2**62), "bad_size")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, f"decoding allocated {peak} bytes"


# ----------------------------------------------------------------------------------------------------- fuzz


def decode_or_reject(data: bytes) -> None:
    try:
        decode(data, run=RUN)
    except Rejected as exc:
        assert exc.reason in REASONS


def test_fuzz_random_bytes() -> None:
    rng = np.random.default_rng(1)
    prefix = bytes(valid_frame()[:HEADER_SIZE])
    for trial in range(2000):
        data = rng.integers(0, 256, int(rng.integers(0, 400)), dtype=np.uint8).tobytes()
        if trial % 2:  # half start with a valid header prefix, so they get past the first checks
            data = prefix[: int(rng.integers(0, HEADER_SIZE + 1))] + data
        decode_or_reject(data)


def test_fuzz_single_byte_mutations() -> None:
    rng = np.random.default_rng(2)
    frame = bytes(encode(Kind.TRAJECTORY, sample_arrays(), run=RUN, meta={"tree_hash": "x"}))  # no digest
    header, _, _ = split(frame)
    table_end = HEADER_SIZE + header.table_len
    valid = 0
    for trial in range(2000):
        # Two thirds land in the header and table, where a flipped byte can change the meaning.
        position = int(rng.integers(0, table_end if trial % 3 else len(frame)))
        mutated = bytearray(frame)
        mutated[position] = (mutated[position] + int(rng.integers(1, 256))) % 256
        try:
            decode(bytes(mutated), run=RUN)
            valid += 1
        except Rejected as exc:
            assert exc.reason in REASONS
    assert 0 < valid < 2000  # some mutations (body bytes) still decode, many do not


def test_fuzz_random_tables() -> None:
    """Well-formed JSON with hostile numbers: huge, negative, zero, beyond int-to-str's 4300-digit limit."""
    rng = np.random.default_rng(3)
    numbers = [0, 1, 3, 4, 12, 48, 64, 2**31, 2**62, 2**63, 2**64, 10**30, 10**4299, 9 * 10**4299, -1, 2.0]
    frame = valid_frame()

    def number() -> Any:
        return numbers[int(rng.integers(len(numbers)))]

    for _ in range(2000):
        entries = [
            [
                str(rng.choice(["obs", "b"])),
                str(rng.choice(["<f4", "|b1", "<i8", "<f2"])),
                [number() for _ in range(int(rng.integers(0, 5)))],
                number(),
                number(),
            ]
            for _ in range(int(rng.integers(1, 4)))
        ]
        decode_or_reject(rebuild(frame, table={"arrays": entries}))


# ---------------------------------------------------------------------------------------------- tree helpers


def test_flatten_unflatten_round_trip() -> None:
    tree = {"params": {"dense": {"kernel": [[1.0, 2.0]], "bias": np.zeros(2)}, "scale": 3}, "step": np.int64(4)}
    flat = flatten(tree)
    assert list(flat) == ["params/dense/kernel", "params/dense/bias", "params/scale", "step"]
    assert all(isinstance(v, np.ndarray) for v in flat.values())
    back = unflatten(flat)
    np.testing.assert_array_equal(back["params"]["dense"]["kernel"], [[1.0, 2.0]])
    assert back["params"]["scale"] == 3 and back["step"] == 4
    assert flatten(flat).keys() == flat.keys()  # already flat: unchanged
    with pytest.raises(ValueError, match="two leaves"):
        flatten({"a/b": 1, "a": {"b": 2}})
    with pytest.raises(ValueError, match="non-empty"):
        flatten({"": 1})
    with pytest.raises(ValueError, match="leaf"):
        unflatten({"a": 1, "a/b": 2})
    with pytest.raises(ValueError, match="leaf"):
        unflatten({"a/b": 1, "a": 2})


def test_tree_hash_covers_structure_not_values() -> None:
    flat = {"w": np.zeros((3, 4), np.float32), "b": np.zeros(4, np.float32)}
    reference = tree_hash(flat)
    assert tree_hash({"b": np.ones(4, np.float32), "w": np.ones((3, 4), np.float32)}) == reference
    assert tree_hash({"w": np.zeros((3, 4), ">f4"), "b": np.zeros(4, np.float32)}) == reference
    assert tree_hash({**flat, "w": np.zeros((4, 3), np.float32)}) != reference
    assert tree_hash({**flat, "w": np.zeros((3, 4), np.float64)}) != reference
    assert tree_hash({"W": flat["w"], "b": flat["b"]}) != reference
    assert tree_hash({**flat, "extra": np.zeros(1)}) != reference


@pytest.mark.parametrize("kind", list(Kind))
def test_control_frames_carry_a_digest_and_data_frames_do_not(kind: Kind) -> None:
    frame = encode(kind, {"w": np.arange(10, dtype=np.float32)}, run=RUN, policy_version=3)
    header = Header._make(HEADER.unpack_from(frame, 0))
    end = -(-(HEADER_SIZE + header.table_len) // ALIGN) * ALIGN + header.body_len
    assert bool(header.flags & FLAG_DIGEST) == (kind in DIGESTED_KINDS)
    assert len(frame) == end + (DIGEST_SIZE if kind in DIGESTED_KINDS else 0)
    assert decode(frame, run=RUN).policy_version == 3


def test_any_flipped_bit_of_a_weights_frame_is_refused() -> None:
    """Every byte of a weights frame, header, table, padding, array bytes and digest, is covered: a flip anywhere
    is refused (by the digest, or earlier by a header check), never decoded into other weights."""
    frame = encode(Kind.WEIGHTS, {"w": np.linspace(-1, 1, 40, dtype=np.float32)}, run=RUN, policy_version=9,
                   meta={"tree_hash": "x"})
    for position in range(len(frame)):
        flipped = bytearray(frame)
        flipped[position] ^= 1 << (position % 8)
        with pytest.raises(Rejected) as info:
            decode(flipped, run=RUN, kinds=Kind.WEIGHTS)
        assert info.value.reason in ("digest", "bad_magic", "bad_version", "wrong_run", "wrong_kind", "bad_table",
                                     "truncated", "bad_size"), (position, info.value)
    body = len(frame) - DIGEST_SIZE - 1  # the last array byte
    flipped = bytearray(frame)
    flipped[body] ^= 0x10
    assert refused(flipped, "digest").detail.startswith("the WEIGHTS frame's bytes do not match")


def test_a_weights_frame_without_its_digest_is_refused() -> None:
    frame = encode(Kind.WEIGHTS, {"w": np.ones(4, np.float32)}, run=RUN)
    header = Header._make(HEADER.unpack_from(frame, 0))
    stripped = HEADER.pack(*header._replace(flags=0)) + bytes(frame[HEADER_SIZE:-DIGEST_SIZE])
    assert "without the digest" in refused(stripped, "digest").detail
