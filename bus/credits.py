"""The credit protocol, both halves: the learner acknowledges to each actor (`learner/credit/<actor>`) the
highest sequence number it has taken off its queue, which frees that actor's credits; an actor sends a batch only
while it has fewer than its credits in flight.

- The frame (`encode_credit`, `decode_credit`) names the actor's incarnation (a restarted actor ignores those
  meant for its predecessor) and carries the learner's epoch in the header (an actor that hears a new epoch
  writes off what it had in flight).
- The learner's half (`Acknowledgements`) sends each acknowledgement as it takes a batch, and every actor's
  latest one again every ACK_REFRESH_S, so a lost acknowledgement never strands credits.
- The actor's half (`CreditLedger`) numbers the batches it sends, counts those in flight, and writes them off
  when they can no longer be acknowledged: a new learner epoch, a learner that was gone and is back, or no
  acknowledgement for longer than its deadline while out of credit (`CreditLedger.deadline_s`).
"""

from __future__ import annotations

import logging
import time
from typing import Any, NamedTuple

from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.session import Bus
from impulse.bus.stamp import Stamp

log = logging.getLogger("impulse.credits")

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


ACK_REFRESH_S = 1.0
"""Every actor's latest acknowledgement is sent again this often, so a lost one never strands its credits."""


class Acknowledgements:
    """The learner's half: the highest sequence number taken from each actor incarnation, sent to that actor."""

    def __init__(self, bus: Bus):
        self.bus = bus
        self._publishers: dict[str, Any] = {}
        self._latest: dict[str, tuple[int, int]] = {}  # actor -> (incarnation, highest seq taken off the queue)
        self._refreshed_at = time.monotonic()

    def acknowledge(self, actor: str, incarnation: int, seq: int) -> None:
        """`actor`'s batch `seq` (of its incarnation `incarnation`) is off the queue: free its credit now."""
        self._latest[actor] = (incarnation, seq)
        self._send(actor)

    def refresh(self) -> None:
        """Send every actor's latest acknowledgement again, if ACK_REFRESH_S have passed since the last time."""
        if time.monotonic() - self._refreshed_at >= ACK_REFRESH_S:
            self._refreshed_at = time.monotonic()
            for actor in self._latest:
                self._send(actor)

    def _send(self, actor: str) -> None:
        publisher = self._publishers.get(actor)
        if publisher is None:
            publisher = self._publishers[actor] = self.bus.publisher(self.bus.keys.credit(actor))
        incarnation, seq = self._latest[actor]
        publisher.put(encode_credit(self.bus.stamp, incarnation, seq))


class CreditLedger:
    """The actor's half: the batches this incarnation sent (`seq`), the highest the learner acknowledged
    (`acked`), and when it last ran out of credit."""

    def __init__(self, incarnation: int, credits: int, timeout_s: float, queued_ahead: int):
        """`credits`: the batches it may have in flight; `timeout_s`: the shortest wait out of credit before they
        are written off; `queued_ahead`: the most batches that may stand before one of its own in the learner's
        queue (every actor's credits), which with the learner's pace bounds how long it may wait there."""
        self.incarnation = incarnation
        self.credits = credits
        self.timeout_s = timeout_s
        self.queued_ahead = queued_ahead
        self.seq = 0
        self.acked = 0
        self.written_off = 0
        self._blocked_since: float | None = None

    @property
    def in_flight(self) -> int:
        return self.seq - self.acked

    def next_seq(self) -> int:
        """Number the next batch sent (from 1)."""
        self.seq += 1
        return self.seq

    def write_off(self) -> None:
        """Count every batch in flight as lost: none of them will be acknowledged."""
        self.written_off += self.in_flight
        self.acked = self.seq
        self._blocked_since = None

    def heard(self, credit: Credit, epoch: int) -> None:
        """An acknowledgement arrived; `epoch`: the learner epoch of the weights this actor follows."""
        if credit.incarnation != self.incarnation:
            return  # meant for an earlier process with this actor's name
        if credit.learner_epoch > epoch >= 0:
            self.write_off()  # a new learner: nothing sent to the old one will be acknowledged
            return
        if self.acked < credit.acked_seq <= self.seq:
            self.acked = credit.acked_seq
            self._blocked_since = None

    def deadline_s(self, seconds_per_version: float | None) -> float:
        """How long to wait out of credit for an acknowledgement before writing the batches in flight off:
        `timeout_s`, or, if longer, the time the learner takes at its recent pace (`seconds_per_version`, None
        before it has one) for the updates that may stand before this actor's batch in its queue and the batch's
        own. So a learner that is merely slow (a loaded machine, a long first compile after a restart) does not
        have its queue written off and overflowed, while one that lost the batch or left is still noticed."""
        if seconds_per_version is None:
            return self.timeout_s
        return max(self.timeout_s, (self.queued_ahead + 1) * seconds_per_version)

    def may_send(self, seconds_per_version: float | None) -> bool:
        """Whether a batch may be sent now; out of credit with no acknowledgement for longer than `deadline_s`,
        the batches in flight are written off (and it may)."""
        if self.in_flight < self.credits:
            return True
        now = time.monotonic()
        if self._blocked_since is None:
            self._blocked_since = now
        deadline = self.deadline_s(seconds_per_version)
        if now - self._blocked_since > deadline:
            log.warning("no acknowledgement for %.0f s: %d batches in flight written off", deadline, self.in_flight)
            self.write_off()
            return True
        return False
