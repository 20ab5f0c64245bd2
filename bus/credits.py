"""Credit frames: the learner's acknowledgement to one actor (`learner/credit/<actor>`) of the highest sequence
number it has taken off its queue, which frees that actor's credits.

The acknowledgement names the actor's incarnation (a restarted actor ignores those meant for its predecessor) and
carries the learner's epoch in the header (an actor that hears a new epoch writes off what it had in flight).
"""

from __future__ import annotations

from typing import NamedTuple

from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.stamp import Stamp

INCARNATION = "incarnation"
ACKED_SEQ = "acked_seq"


def encode_credit(stamp: Stamp, incarnation: int, acked_seq: int) -> bytearray:
    """The acknowledgement of everything up to `acked_seq` from the actor incarnation `incarnation`."""
    return encode(Kind.CREDIT, {}, run=stamp.run, policy_version=stamp.policy_version, learner_epoch=stamp.epoch,
                  seq=acked_seq, meta={INCARNATION: incarnation, ACKED_SEQ: acked_seq})


class Credit(NamedTuple):
    """A received acknowledgement."""

    learner_epoch: int
    incarnation: int
    acked_seq: int


def decode_credit(payload: bytes, run: str) -> Credit:
    """The acknowledgement a frame carries; raises `bus.codec.Rejected` unless both counts are integers."""
    message = decode(payload, run=run, kinds=Kind.CREDIT)
    incarnation, acked = message.meta.get(INCARNATION), message.meta.get(ACKED_SEQ)
    if type(incarnation) is not int or type(acked) is not int:
        raise Rejected("schema", f"an acknowledgement without integer {INCARNATION} and {ACKED_SEQ}")
    return Credit(message.learner_epoch, incarnation, acked)
