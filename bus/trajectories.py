"""Trajectory frames: an actor's batch of experience, to the learner (`actor/traj/<actor>`).

The arrays are the flattened `TrajectoryBatch` (`actors.wire` knows its layout and schema). The header says which
policy acted (the stamp's epoch and version) and the batch's number in the actor's stream; the meta says which
incarnation of the actor sent it, so that the learner's acknowledgements reach that process and no other, and its
index. Data frames carry no digest (`bus.codec`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np
from impulse.bus.codec import Kind, Message, Rejected, decode, encode
from impulse.bus.stamp import Stamp

INCARNATION = "incarnation"
ACTOR_INDEX = "actor"


def encode_trajectory(stamp: Stamp, arrays: Mapping[str, np.ndarray], *, seq: int, incarnation: int,
                      actor_index: int) -> bytearray:
    """Batch number `seq` of actor `actor_index`'s incarnation `incarnation`, acted by the stamp's policy."""
    return encode(Kind.TRAJECTORY, arrays, run=stamp.run, policy_version=stamp.policy_version,
                  learner_epoch=stamp.epoch, seq=seq, meta={INCARNATION: incarnation, ACTOR_INDEX: actor_index})


class Trajectory(NamedTuple):
    """A received trajectory frame: the message (its arrays still to be checked against the learner's schema)
    and the incarnation of the actor that sent it."""

    message: Message
    incarnation: int


def decode_trajectory(payload: bytes, run: str, max_bytes: int) -> Trajectory:
    """The frame and its sender's incarnation; raises `Rejected` for a malformed frame or one without a valid
    incarnation."""
    message = decode(payload, run=run, kinds=Kind.TRAJECTORY, max_bytes=max_bytes)
    incarnation = message.meta.get(INCARNATION)
    if type(incarnation) is not int:
        raise Rejected("schema", f"a trajectory frame without a valid incarnation ({incarnation!r})")
    return Trajectory(message, incarnation)
