"""Trajectory frames: an actor's batch of experience, to the learner (`actor/traj/<actor>`).

The arrays are the flattened `TrajectoryBatch` in one of `actors.wire.TrajectoryWire`'s formats, which knows their
layout and schema: 1, the padded arrays as they are (frames without a `format` in the meta are of this one), or 2,
the compact layout (bits for booleans, entity rows only where they differ from a fill row, optional float16
features). The format number is in the meta (`format`), so actors and a learner set up for different formats
still meet on the same keys (SCHEMA_MAJOR, in every key and header, did not change), where the learner refuses
the foreign frames with the reason "bad_version" (counted like every refusal, `rejected/bad_version`) instead of
misreading them. The header says which
policy acted (the stamp's epoch and version) and the batch's number in the actor's stream; the meta says which
incarnation of the actor sent it, so that the learner's acknowledgements reach that process and no other, and its
index. Data frames carry no digest (`bus.codec`).
"""

from __future__ import annotations

import reprlib
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from impulse.bus.codec import Deferred, Kind, Message, Rejected, decode, encode
from impulse.bus.stamp import Stamp

INCARNATION = "incarnation"
ACTOR_INDEX = "actor"
FORMAT = "format"
FORMAT_WITHOUT_KEY = 1
"""The format of a frame whose meta names none (as every frame before the compact format)."""


_BRIEF = reprlib.Repr()
_BRIEF.maxstring, _BRIEF.maxother = 40, 40


def encode_trajectory(stamp: Stamp, arrays: Mapping[str, np.ndarray | Deferred], *, seq: int, incarnation: int,
                      actor_index: int, layout: int) -> bytearray:
    """Batch number `seq` of actor `actor_index`'s incarnation `incarnation`, acted by the stamp's policy;
    `arrays` are `actors.wire.TrajectoryWire.pack`'s, in format `layout` (the wire's `format`)."""
    return encode(Kind.TRAJECTORY, arrays, run=stamp.run, policy_version=stamp.policy_version,
                  learner_epoch=stamp.epoch, seq=seq,
                  meta={FORMAT: layout, INCARNATION: incarnation, ACTOR_INDEX: actor_index})


class Trajectory(NamedTuple):
    """A received trajectory frame: the message (its arrays still to be checked against the learner's schema)
    and the incarnation of the actor that sent it."""

    message: Message
    incarnation: int


def decode_trajectory(payload: bytes, run: str, max_bytes: int, layout: int) -> Trajectory:
    """The frame and its sender's incarnation; raises `Rejected` for a malformed frame, one of another format than
    `layout` ("bad_version") or one without a valid incarnation."""
    message = decode(payload, run=run, kinds=Kind.TRAJECTORY, max_bytes=max_bytes)
    version = message.meta.get(FORMAT, FORMAT_WITHOUT_KEY)
    if version != layout or type(version) is not int:
        raise Rejected("bad_version", f"trajectory format {_BRIEF.repr(version)}, this learner reads {layout} "
                                      "(bus.wire_compact must be the same for the whole run)")
    incarnation = message.meta.get(INCARNATION)
    if type(incarnation) is not int:
        raise Rejected("schema", f"a trajectory frame without a valid incarnation ({incarnation!r})")
    return Trajectory(message, incarnation)
