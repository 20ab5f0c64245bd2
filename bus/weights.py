"""Weights frames: the learner's policy parameters, to every actor (`learner/weights/policy`, cached for late
joiners, and the `learner/weights/latest` queryable).

The arrays are the flattened parameters; the header carries the learner's epoch and the policy version; the meta
carries the parameters' tree hash (an actor refuses another network's weights, `bus.schema`) and the learner's
clock at publication (actors measure the broadcast's latency) and its instance nonce (followers adopt weights only
from the learner instance whose liveliness token they follow). Weights are a control frame: a digest covers every
byte (`bus.codec`), and actors adopt only newer ones (`actors.follow`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from impulse.bus.codec import TREE_HASH_META, Kind, Message, decode, encode
from impulse.bus.stamp import Stamp

PUBLISHED_AT = "published_at"
"""Meta: the learner's wall-clock time at publication."""
LEARNER_NONCE = "learner_nonce"
"""Meta: the publishing learner process's instance nonce (`bus.keys.INSTANCE`)."""


def encode_weights(stamp: Stamp, arrays: Mapping[str, np.ndarray], tree_hash: str) -> bytes:
    """The stamp's policy version (of its epoch) as a weights frame, stamped with the time now."""
    return bytes(encode(Kind.WEIGHTS, arrays, run=stamp.run, policy_version=stamp.policy_version,
                        learner_epoch=stamp.epoch, meta={TREE_HASH_META: tree_hash, PUBLISHED_AT: time.time(),
                                                         LEARNER_NONCE: stamp.nonce}))


class Weights(NamedTuple):
    """A received weights frame (arrays still to be checked against the actor's schema) and when it was
    published (None if the frame does not say)."""

    message: Message
    published_at: float | None
    nonce: str | None = None
    """The instance nonce of the learner that published it (None if the frame names none)."""

    @property
    def order(self) -> tuple[int, int]:
        """(learner epoch, policy version): what newer means."""
        return self.message.learner_epoch, self.message.policy_version


def decode_weights(payload: bytes, run: str) -> Weights:
    """The weights a frame carries; raises `bus.codec.Rejected` for a malformed, foreign or corrupted one."""
    message = decode(payload, run=run, kinds=Kind.WEIGHTS)
    published = message.meta.get(PUBLISHED_AT)
    nonce = message.meta.get(LEARNER_NONCE)
    return Weights(message, published if isinstance(published, float) and math.isfinite(published) else None,
                   nonce if isinstance(nonce, str) and nonce else None)
