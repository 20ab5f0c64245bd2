"""The compact trajectory format (`actors.wire.TrajectoryWire`): real rollout batches come back bit for bit at the
learner's padded shapes, with unused entity rows and booleans compacted; float16 only rounds the features; a frame
of the previous format is refused and counted by reason; hostile compact frames are refused, never misread."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from impulse.actors.wire import FILL, ROWS, TrajectoryWire
from impulse.benchmarks.distributed import rollout_batch
from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.rejects import RejectCounter
from impulse.bus.stamp import Stamp
from impulse.bus.trajectories import ACTOR_INDEX, INCARNATION, decode_trajectory, encode_trajectory
from impulse.engine.pytree import tree_arrays

RUN = "compact-test"
STAMP = Stamp(RUN, epoch=1, policy_version=3)


def same_bits(sent, got, what: str = "") -> None:
    sent, got = np.atleast_1d(np.asarray(sent)), np.atleast_1d(np.asarray(got))
    assert sent.dtype == got.dtype and sent.shape == got.shape, what
    np.testing.assert_array_equal(sent.view(np.uint8), got.view(np.uint8), err_msg=what)


def send(wire: TrajectoryWire, batch, seq: int = 1) -> bytes:
    return bytes(encode_trajectory(STAMP, wire.pack(tree_arrays(batch)), seq=seq, incarnation=7, actor_index=0,
                                   layout=wire.format))


def receive(wire: TrajectoryWire, frame: bytes):
    return wire.checked(decode_trajectory(frame, RUN, 1 << 30, wire.format).message)


@pytest.fixture(scope="module", params=["entity", "symbolic"])
def rolled(request):
    """A batch of a real rollout on S levels (random initial weights), the one the bytes benchmark's test uses."""
    return rollout_batch("s", request.param, num_envs=2, num_steps=4)


def test_real_batches_round_trip_bit_for_bit_and_smaller(rolled):
    spec, batch = rolled
    wire = TrajectoryWire(batch, spec.sizes, compact=True)
    frame = send(wire, batch)
    got = receive(wire, frame)
    sent_leaves, got_leaves = jax.tree.leaves(batch), jax.tree.leaves(got)
    for sent, back in zip(sent_leaves, got_leaves, strict=True):
        same_bits(sent, back)
    padded = len(encode(Kind.TRAJECTORY, tree_arrays(batch), run=RUN))
    message = decode(frame, run=RUN)
    cut = [name for name in message.arrays if name.endswith(ROWS)]
    assert cut, "no array was cut by rows"
    if spec.observation == "entity":  # unused entity rows are left out
        assert len(frame) < padded
    else:  # the flat observation has no entity rows; what rows a batch of 2 x 4 steps saves depends on its levels
        # (smaller on Kinetix's shared S levels, 128 bytes larger on our hand-made ones): the row masks are all it
        # can add, one 64-byte-aligned array each at most
        assert len(frame) <= padded + 64 * len(cut), (len(frame), padded, len(cut))
    assert message.arrays["steps/done"].dtype == np.uint8  # booleans as bits
    if spec.observation == "entity":  # the hand-made levels leave slots unused: fewer rows than the padding
        rows = np.unpackbits(message.arrays["steps/obs/polygons" + ROWS])
        assert 0 < rows.sum() < rows.size


def test_rows_that_differ_from_the_fill_travel_even_when_inactive(rolled):
    """Exact whatever a level leaves in an unused slot: an inactive row unlike the others is sent, not filled."""
    spec, batch = rolled
    arrays = {name: np.array(a) for name, a in tree_arrays(batch).items()}
    name = "steps/obs/polygons" if spec.observation == "entity" else "steps/obs"
    arrays[name][1, 1, -1] = -0.0  # a negative zero: equal to 0.0 as a float, not as bits
    arrays[name][0, 0, 0] = 1e-3
    wire = TrajectoryWire(batch, spec.sizes, compact=True)
    frame = bytes(encode_trajectory(STAMP, wire.pack(arrays), seq=1, incarnation=7, actor_index=0,
                                    layout=wire.format))
    back = wire.unpack(decode_trajectory(frame, RUN, 1 << 30, wire.format).message)
    for key, value in arrays.items():
        same_bits(value, back[key], key)


def test_float16_rounds_only_the_features(rolled):
    spec, batch = rolled
    wire = TrajectoryWire(batch, spec.sizes, compact=True, float16=True)
    frame = send(wire, batch)
    assert len(frame) < len(send(TrajectoryWire(batch, spec.sizes, compact=True), batch))
    got = tree_arrays(receive(wire, frame))
    for name, sent in tree_arrays(batch).items():
        if name in wire.fields and wire.fields[name].half:
            rounded = sent.astype(np.float16).astype(np.float32)
            assert got[name].dtype == np.float32
            # Rows sent are rounded to float16; rows standing in as the fill (unused slots) stay exact.
            assert np.all((got[name] == rounded) | (got[name] == sent)), name
            assert np.any(got[name] != sent), name
        else:
            np.testing.assert_array_equal(got[name], sent, err_msg=name)


def test_out_of_range_features_stay_float32(rolled):
    spec, batch = rolled
    arrays = {name: np.array(a) for name, a in tree_arrays(batch).items()}
    name = "steps/obs/polygons" if spec.observation == "entity" else "steps/obs"
    arrays[name][0, 0, 0] = 1e6  # beyond float16's range
    wire = TrajectoryWire(batch, spec.sizes, compact=True, float16=True)
    message = decode(bytes(encode_trajectory(STAMP, wire.pack(arrays), seq=1, incarnation=7, actor_index=0,
                                             layout=wire.format)), run=RUN)
    assert message.arrays[name].dtype == np.float32
    np.testing.assert_array_equal(wire.unpack(message)[name], arrays[name])


def test_a_frame_of_the_other_format_is_refused_and_counted(rolled):
    """A learner reads the one format its run is set up for (`bus.wire_compact`); a frame of the other is
    refused as "bad_version", never misread. A frame as builds before the compact format sent it (padded, no
    `format` in the meta) is format 1, which padded learners still read."""
    spec, batch = rolled
    compact, padded = TrajectoryWire(batch, spec.sizes, compact=True), TrajectoryWire(batch, spec.sizes)
    old = bytes(encode(Kind.TRAJECTORY, tree_arrays(batch), run=RUN, policy_version=3, learner_epoch=1, seq=1,
                       meta={INCARNATION: 7, ACTOR_INDEX: 0}))
    rejects = RejectCounter()
    for wire, frame in ((compact, old), (compact, send(compact, batch)), (padded, send(compact, batch)),
                        (padded, send(padded, batch)), (padded, old)):
        try:  # as the learner's `_ingest` reads a frame
            receive(wire, frame)
        except Rejected as err:
            rejects.record(err.reason, "actor-0", err.detail)
    assert rejects.counts() == {"bad_version": 2}
    for sent, got in zip(jax.tree.leaves(batch), jax.tree.leaves(receive(padded, old)), strict=True):
        np.testing.assert_array_equal(np.asarray(sent), np.asarray(got))
    # Even if its format were not stated, padded booleans could not be misread as bits.
    with pytest.raises(Rejected) as refused:
        compact.checked(decode(old, run=RUN))
    assert refused.value.reason in {"bad_dtype", "bad_shape", "schema"}


def test_inconsistent_compact_frames_are_refused(rolled):
    spec, batch = rolled
    wire = TrajectoryWire(batch, spec.sizes, compact=True)
    name = "steps/obs/polygons" if spec.observation == "entity" else "steps/obs"
    good = decode(send(wire, batch), run=RUN)

    def with_arrays(**changes):
        arrays = dict(good.arrays)
        for key, value in changes.items():
            key = key.replace("__", ":").replace("_SLASH_", "/")
            if value is None:
                arrays.pop(key)
            else:
                arrays[key] = value
        return type(good)(good.kind, good.policy_version, good.learner_epoch, good.seq, good.meta, arrays)

    data, rows, fill = good.arrays[name], good.arrays[name + ROWS], good.arrays[name + FILL]
    key = name.replace("/", "_SLASH_")
    cases = {
        "schema": {key: None},
        "bad_shape": {key: data[:-1]},
        "bad_dtype": {key + "__fill": fill.astype(np.float64)},
    }
    for reason, change in cases.items():
        with pytest.raises(Rejected) as refused:
            wire.checked(with_arrays(**change))
        assert refused.value.reason == reason, (reason, refused.value)
    with pytest.raises(Rejected) as refused:
        wire.checked(with_arrays(**{key + "__rows": np.zeros_like(rows)}))  # no rows selected, data left over
    assert refused.value.reason == "bad_shape"
    nan = np.array(data)
    nan[0] = np.nan
    with pytest.raises(Rejected) as refused:
        wire.checked(with_arrays(**{key: nan}))
    assert refused.value.reason == "non_finite"
