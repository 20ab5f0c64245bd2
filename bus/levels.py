"""Level frames, both ways between actors and the curriculum service:

- a level batch (LEVELS): the curriculum's answer to an actor's query on `curriculum/levels/sample` (the levels,
  whether each is trained on, where each came from), numbered by the service's samples so far;
- level results (LEVEL_RESULTS): an actor's per-level outcomes on `actor/results/<actor>`, stamped with the
  policy that played them;
- a played level batch (LEVELS again): the levels an actor is about to play, on `actor/played/<actor>`, for the
  recorder (`learner.recorder`), sent when they change, when a recorder (re)appears, and every
  PLAYED_LEVELS_EVERY_S.

The arrays' layout and schemas belong to the curriculum (`curriculum.wire`); this module only frames them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from impulse.bus.codec import Kind, Message, decode, encode
from impulse.bus.stamp import Stamp

LEVEL_QUERY_TIMEOUT_S = 10.0
"""How long an actor waits for the answer to one level query before it asks again."""
WAIT_PARAMETER = "wait_s"
"""The level query's parameter in which an asker says how long it waits for the answer (seconds). The curriculum
service refuses a query that has waited half that long in its queue (`level_query_expired`) instead of serving it:
the rest of the wait may not cover a sample, and a service that serves queries whose askers have gone (each
asking again after its wait) falls behind for good, serving every batch in vain while the actors wait. A query
without it (a one-shot `get` from a tool or a test) never expires."""

PLAYED_LEVELS_EVERY_S = 10.0
"""An actor publishes an unchanged level batch (a fixed level set) again this often while a recorder listens, so
that a recorder started later hears it too."""
PLAYED_LEVEL_WAIT_S = PLAYED_LEVELS_EVERY_S + 5.0
"""How long the recorder holds a whole episode whose level it has not heard before writing it without one: the
level is at most one repeat away (`PLAYED_LEVELS_EVERY_S`) unless its message was lost."""


def level_query_expired(parameters: Mapping[str, str], waited_s: float) -> bool:
    """Whether a level query with these `parameters` that has waited `waited_s` in the queue is past serving: its
    asker said how long it waits (`WAIT_PARAMETER`) and half of that is gone. A malformed value counts as unsaid
    (it only ever concerns the asker's own query)."""
    try:
        wait_s = float(parameters.get(WAIT_PARAMETER, "inf"))
    except ValueError:
        return False
    return wait_s > 0 and waited_s >= wait_s / 2


def encode_level_batch(stamp: Stamp, arrays: Mapping[str, np.ndarray]) -> bytearray:
    """A batch of levels served now (numbered by the stamp's LEVELS sequence)."""
    return encode(Kind.LEVELS, arrays, run=stamp.run, seq=stamp.next_seq(Kind.LEVELS))


def decode_level_batch(payload: bytes, run: str) -> Message:
    """The level batch a frame carries (arrays still to be checked); raises `bus.codec.Rejected` if malformed."""
    return decode(payload, run=run, kinds=Kind.LEVELS)


def encode_level_results(stamp: Stamp, arrays: Mapping[str, np.ndarray], seq: int) -> bytearray:
    """Per-level results of the stamp's policy, sent with trajectory batch number `seq`."""
    return encode(Kind.LEVEL_RESULTS, arrays, run=stamp.run, policy_version=stamp.policy_version,
                  learner_epoch=stamp.epoch, seq=seq)


def decode_level_results(payload: bytes, run: str) -> Message:
    """The results a frame carries (arrays still to be checked); raises `bus.codec.Rejected` if malformed."""
    return decode(payload, run=run, kinds=Kind.LEVEL_RESULTS)
