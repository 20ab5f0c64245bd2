"""The learner's intake: trajectory frames from the bus to the batch the next update trains on (the learner
service's steps 2 and 3, `learner.service`).

- `ingest` takes every frame waiting in the bounded inbox and reads its header in the learner's thread (never in a
  zenoh callback): a malformed or foreign frame is refused and counted by reason; a duplicate sequence number is
  refused; a gap in an actor's sequence (after the first batch of it this learner sees) is counted as lost. The
  frame joins the ready queue as it came off the bus (the compact format's bytes, not the full arrays); a full
  queue pushes out its oldest frame, counted as an overflow.
- `take` hands out the oldest frame fit to train on, unpacked and checked, and acknowledges every frame it takes
  off the queue to its actor (`bus.credits.Acknowledgements`), which frees that actor's credit. A frame acted by
  weights of an earlier learner epoch, or too old or too new for the learner's policy (`learner.update.
  check_policy_lag`, judged from the header before the arrays are unpacked and again from the batch's own
  behaviour version after), is dropped and counted instead; so is one whose arrays do not fit the batch's schema.
  So an overloaded learner spends nothing on the frames it drops.

After STALE_ALARM_AFTER stale frames in a row, the intake warns that the actors do not act with the learner's
weights and asks for them to be published again (`take`'s `republish`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import NamedTuple

from impulse.actors.trajectory import TrajectoryBatch
from impulse.actors.wire import TrajectoryWire
from impulse.bus.codec import Message, Rejected
from impulse.bus.credits import Acknowledgements
from impulse.bus.session import Bus
from impulse.bus.trajectories import decode_trajectory
from impulse.learner.update import check_policy_lag

log = logging.getLogger("impulse.learner")

STALE_ALARM_AFTER = 20
"""Batches dropped as stale in a row (none trained on between them) after which the intake warns that the actors
do not act with the learner's weights, and has them published again; repeated at most every STALE_ALARM_EVERY_S."""
STALE_ALARM_EVERY_S = 60.0
DROP_COUNTS = ("dropped_stale", "dropped_old_epoch", "dropped_overflow", "dropped_inbox_full", "lost")
"""The intake's drop counters: acted by weights too old, or of an earlier learner epoch; pushed out of the ready
queue; refused by a full trajectory inbox; missing from an actor's sequence (lost on the way)."""


class Queued(NamedTuple):
    """A trajectory frame waiting to be trained on: which actor (incarnation) sent it, and the frame, its header
    read and its arrays not yet unpacked or checked (`TrajectoryIntake.take` does that for the frames it hands out
    only)."""

    actor: str
    incarnation: int
    message: Message


class Taken(NamedTuple):
    """A batch fit to train on: its actor, its frame's header, the batch, and its policy lag."""

    actor: str
    message: Message
    batch: TrajectoryBatch
    lag: int


@dataclasses.dataclass
class Ingested:
    """The intake since it started: trajectory frames accepted into its queue, their bytes, and the time its thread
    spent taking frames out of zenoh and reading their headers (refused ones included); then the frames unpacked
    and checked when taken for an update, and the time that took. Together they bound the frames per second one
    learner can take in besides its updates."""

    frames: int = 0
    bytes: int = 0
    seconds: float = 0.0
    unpacked: int = 0
    unpack_seconds: float = 0.0

    def status(self) -> dict[str, float]:
        return {"frames": self.frames, "mb": round(self.bytes / 2**20, 1), "seconds": round(self.seconds, 3),
                "unpacked": self.unpacked, "unpack_seconds": round(self.unpack_seconds, 3)}


class TrajectoryIntake:
    """The inbox, the ready queue and the acknowledgements of one learner process (module docstring)."""

    def __init__(self, bus: Bus, wire: TrajectoryWire, *, capacity: int, max_policy_lag: int, counts: Counter[str],
                 serves: Callable[[str], bool] | None = None):
        """`capacity`: frames the inbox and the ready queue each hold; `counts`: the learner's counters, to which
        the intake adds its DROP_COUNTS and `stale_alarms` (they are kept in checkpoints); `serves`: on several
        hosts, whether this process trains on an actor's batches (frames of other actors are left to the other
        processes)."""
        self.bus = bus
        self.wire = wire
        self.max_policy_lag = max_policy_lag
        self.counts = counts
        self.serves = serves
        self.acks = Acknowledgements(bus)
        self._inbox = bus.inbox(bus.keys.traj_all, capacity)
        self._inbox_dropped_before = counts["dropped_inbox_full"]
        self._ready: deque[Queued] = deque()
        self._ready_limit = capacity
        self._last_seq: dict[tuple[str, int], int] = {}
        self.ingested = Ingested()
        self.lags: Counter[int] = Counter()
        self.actor_lag: dict[str, int] = {}
        self.stale_streak = 0  # batches dropped as stale since the last one handed out
        self._stale_versions: Counter[int] = Counter()  # ... and the versions that acted them
        self._stale_alarm_at = -float("inf")

    @property
    def queued(self) -> int:
        """Frames waiting in the ready queue."""
        return len(self._ready)

    def ingest(self) -> None:
        """Move every frame waiting in the inbox to the ready queue, header read (module docstring)."""
        started = time.perf_counter()
        waiting = self._inbox.poll()
        for received in waiting:
            source = received.key.rsplit("/", 1)[-1]  # the actor, as the key names it (`Keys.traj`)
            if self.serves is not None and not self.serves(source):
                continue  # another learner process's actor
            try:
                message, incarnation = decode_trajectory(received.payload, self.bus.keys.run,
                                                         self.wire.max_frame_bytes, self.wire.format)
                stream = (source, incarnation)
                last = self._last_seq.get(stream)
                if last is not None and message.seq <= last:
                    raise Rejected("duplicate", f"sequence number {message.seq} after {last}")
            except Rejected as err:
                self.bus.rejects.record(err.reason, source, err.detail)
                continue
            # Gaps count from the first batch of a stream this learner sees: a restarted learner joins streams
            # midway, and what was sent before it started was not lost to it.
            if last is not None and message.seq > last + 1:
                self.counts["lost"] += message.seq - last - 1
            self._last_seq[stream] = message.seq
            if len(self._ready) >= self._ready_limit:
                dropped = self._ready.popleft()
                self.counts["dropped_overflow"] += 1
                self.acks.acknowledge(dropped.actor, dropped.incarnation, dropped.message.seq)
            self._ready.append(Queued(source, incarnation, message))
            self.ingested.frames += 1
            self.ingested.bytes += len(received.payload)
        if waiting:
            self.ingested.seconds += time.perf_counter() - started
        self.counts["dropped_inbox_full"] = self._inbox_dropped_before + self._inbox.dropped

    def take(self, epoch: int, version: int, republish: Callable[[], None]) -> Taken | None:
        """The oldest batch fit to train on for the learner at `epoch` and policy `version`, unpacked and checked,
        acknowledging everything taken off the queue (module docstring); None when none is. `republish`: publish
        the learner's weights again (the stale alarm's remedy)."""
        while self._ready:
            actor, incarnation, message = self._ready.popleft()
            self.acks.acknowledge(actor, incarnation, message.seq)
            if message.learner_epoch != epoch:
                self.counts["dropped_old_epoch"] += 1
                continue
            if not check_policy_lag(message.policy_version, version, self.max_policy_lag).accepted:
                self._drop_stale(message.policy_version, version, republish)
                continue
            started = time.perf_counter()
            try:
                batch = self.wire.checked(message)
            except Rejected as err:
                self.bus.rejects.record(err.reason, actor, err.detail)
                continue
            finally:
                self.ingested.unpacked += 1
                self.ingested.unpack_seconds += time.perf_counter() - started
            lag, accepted = check_policy_lag(int(batch.behaviour_version), version, self.max_policy_lag)
            if not accepted:
                self._drop_stale(int(batch.behaviour_version), version, republish)
                continue
            self.stale_streak = 0
            self._stale_versions.clear()
            self.lags[lag] += 1
            self.actor_lag[actor] = lag
            return Taken(actor, message, batch, lag)
        return None

    def _drop_stale(self, behaviour_version: int, version: int, republish: Callable[[], None]) -> None:
        """Count a batch dropped as too old (or ahead of the learner); after STALE_ALARM_AFTER in a row, warn and
        have the weights published again (a follower that refuses them all re-syncs by query: `actors.follow`)."""
        self.counts["dropped_stale"] += 1
        self.stale_streak += 1
        self._stale_versions[behaviour_version] += 1
        now = time.monotonic()
        if self.stale_streak >= STALE_ALARM_AFTER and now - self._stale_alarm_at >= STALE_ALARM_EVERY_S:
            self._stale_alarm_at = now
            self.counts["stale_alarms"] += 1
            acted = ", ".join(str(v) for v, _ in self._stale_versions.most_common(3))
            log.warning("the last %d batches were all dropped as stale: they were acted by policy versions %s while "
                        "this learner is at %d (ppo.max_policy_lag=%d); the actors are not acting with its weights: "
                        "publishing them again", self.stale_streak, acted, version, self.max_policy_lag)
            republish()
