"""Following the learner: adopting its newest weights and noticing whether it is there. The actor process, the
evaluator and the curriculum's candidate scorer follow the learner the same way; the recorder follows its presence.

Which learner. Each learner process draws a random nonce at start, declares a liveliness token for it
(`<root>/learner/alive/instance-<nonce>`, `bus.keys.INSTANCE`) and puts it in every weights frame. A follower
follows one instance at a time: the first whose token it sees, and, once that token is gone, the next one alive
(a restarted learner). Weights of any other instance, or naming none, are refused and counted as
`foreign_learner`: a process left over from an earlier run, a second learner started under the same run name or a
stray frame cannot take the followers over, even on the open one-machine bus where anyone may publish on the
learner's keys (a router with access control keeps everyone else off them; docs/multi-host.md). Two instances
alive at once are reported (`learners_seen` on the status line, and a warning): one of them should not be there.
Frames that arrive before any instance token are kept (the newest) until one is seen.

Weights. A weights frame is adopted only when its digest matches (`bus.codec`), it comes from the followed
instance, it fits the network (the schema made from the follower's parameter template), and its (learner epoch,
policy version) is strictly newer than the weights held from that instance; a replayed older frame is refused as
stale and one equal to the weights held is ignored (counted as repeated). A new instance's weights are adopted
whatever their order. Every frame that reaches the follower's inbox is checked and, if refused, counted by reason;
frames the inbox itself had to drop before they were looked at (it holds WEIGHTS_INBOX frames) are counted as
`dropped_weights_overwritten`. Until the first weights arrive, the follower also asks the learner's queryable
every WEIGHTS_QUERY_EVERY_S (the cached broadcast usually arrives first).

Re-syncing. A follower that has refused every weights frame for RESYNC_AFTER_S while they kept coming (it holds a
version the learner is not at: a bug, or a learner that went back) says so in a warning, counts a `resync`, and
asks the learner's queryable, adopting its answer as the learner's current weights whatever their version.

The learner's presence and its word. The follower watches the learner's liveliness token and its status lines (on
the learner's own status key). The learner has finished the run when its latest status says so and its token is
gone: a finished learner publishes that status and leaves, while a forged "finished" with the learner still there
changes nothing, and the learner's next status overwrites it.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import Any, NamedTuple

import jax

from impulse.actors.wire import weights_schema
from impulse.bus.codec import Rejected
from impulse.bus.keys import LEARNER, Keys
from impulse.bus.schema import check
from impulse.bus.session import Bus
from impulse.bus.status import read_status
from impulse.bus.weights import Weights, decode_weights
from impulse.engine.pytree import tree_from_arrays

log = logging.getLogger("impulse.follow")

WEIGHTS_QUERY_EVERY_S = 2.0
"""While it has no weights, a follower asks the learner's queryable this often."""
LATENCY_WINDOW = 100
"""Weight broadcasts whose publish-to-adopted latency `latency_ms` summarises."""
PACE_WINDOW = 8
"""Adoptions over which `seconds_per_version` measures the learner's pace."""
WEIGHTS_INBOX = 8
"""Weights frames waiting between two polls; more are dropped (oldest first) and counted."""
RESYNC_AFTER_S = 30.0
RESYNC_MIN_REFUSALS = 3
"""A follower that has refused every weights frame for RESYNC_AFTER_S, and at least RESYNC_MIN_REFUSALS of them,
asks the learner for its current weights."""


class FollowEvents(NamedTuple):
    """What one `LearnerFollower.poll` saw."""

    adopted: bool
    """New weights were adopted."""
    new_epoch: bool
    """... and they are of another learner epoch than the weights held before (a restarted learner)."""
    learner_back: bool
    """The learner's liveliness token came back after it had gone (a broken link, a restarted router or learner)."""


class LearnerPresence:
    """Whether the learner is there (its liveliness token), which learner instances are alive (their instance
    tokens, in the order first seen), and whether it has finished the run (its latest status says so and its token
    is gone: see the module docstring), for every process that follows the learner, with or without its weights
    (the recorder). A learner on several hosts is its leader, named `learner`; the tokens and statuses of its other
    processes are not the learner's."""

    def __init__(self, bus: Bus):
        self.bus = bus
        self._tokens = bus.watch_alive(bus.keys.alive_pattern(LEARNER))
        self._statuses = bus.inbox(bus.keys.status_pattern(LEARNER), 4, drop_oldest=True)
        self.present = False
        self.instances: list[str] = []
        """Nonces of the learner instances whose tokens are alive, the first seen first."""
        self._away = False
        self._says_finished = False

    @property
    def finished(self) -> bool:
        """The learner's latest status says the run is finished and the learner has left."""
        return self._says_finished and not self.present

    def poll(self) -> bool:
        """Note the learner's comings and goings and its word; whether it came back after it had gone."""
        back = False
        for key, alive in self._tokens.poll():
            ident = self.bus.keys.parse_alive(key)[1]
            nonce = Keys.instance_nonce(ident)
            if nonce is not None:
                if alive and nonce not in self.instances:
                    self.instances.append(nonce)
                elif not alive and nonce in self.instances:
                    self.instances.remove(nonce)
                continue
            if ident != LEARNER:
                continue  # another process of a learner on several hosts (`learner-1`, ...): the leader speaks
            self.present = alive
            if not alive:
                self._away = True
            elif self._away:
                self._away = False
                back = True
        for received in self._statuses.poll():
            try:
                status = read_status(received, self.bus.keys).status
            except Rejected as err:
                self.bus.rejects.record(err.reason, received.key, err.detail)
                continue
            if status.get("name", LEARNER) != LEARNER:
                continue
            self._says_finished = status.get("finished") is True
        return back


class LearnerFollower:
    """The learner's newest weights (`params`, `epoch`, `version`; None and -1 before the first) and its presence,
    as one process sees them (see the module docstring). Refused frames are counted by the bus's reject counter;
    `counts` holds what was adopted, repeated, overwritten in the inbox and re-synced."""

    def __init__(self, bus: Bus, params_template: Any):
        self.bus = bus
        self._template = params_template
        self._schema = weights_schema(params_template)
        keys = bus.keys
        self._weights = bus.inbox(keys.weights_policy, WEIGHTS_INBOX, drop_oldest=True, latest=True)
        self.learner = LearnerPresence(bus)
        self.params: Any = None
        self.epoch = -1
        self.version = -1
        self.followed: str | None = None
        """The nonce of the learner instance whose weights are adopted (None before its token is seen)."""
        self.counts = {"weights_adopted": 0, "weights_by_query": 0, "weights_repeated": 0,
                       "dropped_weights_overwritten": 0, "resyncs": 0, "learners_seen": 0}
        self._held_from: str | None = None  # the instance that published the weights held
        self._unplaced: Weights | None = None  # the newest frame that came before any instance token
        self._last_query = -float("inf")
        self._refusing_since: float | None = None  # the first refusal since the last adoption
        self._refusals = 0  # ... and how many since
        self._warned_about: frozenset[str] = frozenset()
        self._latency_ms: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self._adoptions: deque[tuple[float, int]] = deque(maxlen=PACE_WINDOW)  # (when, version), this epoch

    @property
    def seconds_per_version(self) -> float | None:
        """The learner's recent pace: seconds per policy version (one version per update), over the last
        PACE_WINDOW adoptions of this epoch; None before two. Versions count updates, so the pace holds however
        seldom this process looks (an actor adopts only between rollouts)."""
        if len(self._adoptions) < 2:
            return None
        (first_at, first_version), (last_at, last_version) = self._adoptions[0], self._adoptions[-1]
        return (last_at - first_at) / (last_version - first_version)

    @property
    def learner_finished(self) -> bool:
        """Whether the learner's latest status says the run is finished and the learner has left."""
        return self.learner.finished

    def latency_ms(self) -> dict[str, float]:
        """Publish-to-adopted latency of the latest broadcasts: {"n", "p50", "max"} (empty before any)."""
        if not self._latency_ms:
            return {}
        ordered = sorted(self._latency_ms)
        return {"n": len(ordered), "p50": ordered[len(ordered) // 2], "max": ordered[-1]}

    def poll(self) -> FollowEvents:
        """Note the learner's comings and goings and its word, check every weights frame that arrived and adopt
        the newest acceptable one (asking for weights while there are none yet, or to re-sync)."""
        learner_back = self.learner.poll()
        self._choose_instance()
        frames = self._decoded(received.payload for received in self._weights.poll())
        self.counts["dropped_weights_overwritten"] = self._weights.dropped
        queried = False
        if self.params is None and time.monotonic() - self._last_query >= WEIGHTS_QUERY_EVERY_S:
            self._last_query = time.monotonic()
            answers = self._decoded(self.bus.get(self.bus.keys.weights_latest, timeout_s=1.0)[-1:])
            queried = bool(answers) and not frames
            frames = answers + frames
        if self._unplaced is not None and self.followed is not None:
            frames, self._unplaced = [self._unplaced, *frames], None
        epoch_before = self.epoch
        acceptable = []
        for weights in frames:
            if self.followed is None:
                self._unplaced = weights  # no instance token seen yet: kept until one is
                continue
            try:
                if self._acceptable(weights):
                    acceptable.append(weights)
            except Rejected as err:
                self.bus.rejects.record(err.reason, "weights", err.detail)
                self._refusals += 1
                if self._refusing_since is None:
                    self._refusing_since = time.monotonic()
        adopted = False
        if acceptable:  # the newest of them (the others were checked too, and are older)
            first = self.params is None
            self._take(max(acceptable, key=lambda weights: weights.order))
            adopted = True
            if queried:
                self.counts["weights_by_query"] += 1
            if first:
                log.info("adopted the learner's current weights %s: version %d, epoch %d",
                         "by query" if queried else "from its cached broadcast", self.version, self.epoch)
        elif self._refusals >= RESYNC_MIN_REFUSALS and self._refusing_since is not None and \
                time.monotonic() - self._refusing_since >= RESYNC_AFTER_S:
            adopted = self._resync()
        new_epoch = adopted and epoch_before >= 0 and self.epoch != epoch_before
        return FollowEvents(adopted, new_epoch, learner_back)

    def _decoded(self, payloads: Any) -> list[Weights]:
        """The frames whose envelope is intact (digest, run, kind); the others are counted by reason."""
        frames = []
        for payload in payloads:
            try:
                frames.append(decode_weights(payload, self.bus.keys.run))
            except Rejected as err:
                self.bus.rejects.record(err.reason, "weights", err.detail)
        return frames

    def _choose_instance(self) -> None:
        """Follow the first learner instance seen, and the next one once its token is gone; warn about several."""
        alive = self.learner.instances
        self.counts["learners_seen"] = len(alive)
        if alive and self.followed not in alive:
            before, self.followed = self.followed, alive[0]
            if before is not None:
                log.info("the learner instance %s is gone: following %s", before, self.followed)
        if len(alive) > 1 and frozenset(alive) != self._warned_about:
            self._warned_about = frozenset(alive)
            log.warning("%d learner instances of run %s are on the bus (%s): following %s and refusing the others' "
                        "weights; a learner of an earlier run or a second one under the same name should be stopped",
                        len(alive), self.bus.keys.run, ", ".join(alive), self.followed)

    def _acceptable(self, weights: Weights, resync: bool = False) -> bool:
        """Whether checked weights may be adopted: the followed instance's and newer than those held (any order
        from an instance not held before, or when re-syncing); False for a repeat. Raises `Rejected`."""
        if weights.nonce != self.followed:
            raise Rejected("foreign_learner", f"weights of learner instance {weights.nonce or '(none named)'}, not "
                           f"of the followed {self.followed}")
        check(weights.message, self._schema)
        held, offered = (self.epoch, self.version), weights.order
        if self._held_from != weights.nonce or resync:
            return True
        if offered == held:
            self.counts["weights_repeated"] += 1  # the cached broadcast again (a reconnection), or a copy
            return False
        if offered < held:
            raise Rejected("stale", f"weights of epoch {offered[0]} version {offered[1]}, older than the epoch "
                           f"{held[0]} version {held[1]} held (a replay?)")
        return True

    def _take(self, weights: Weights) -> None:
        """Adopt weights `_acceptable` passed."""
        message = weights.message
        same_instance = self._held_from == weights.nonce
        self.params = jax.device_put(tree_from_arrays(message.arrays, self._template))
        if message.learner_epoch != self.epoch and self.epoch >= 0:
            log.info("the learner restarted (epoch %d -> %d)", self.epoch, message.learner_epoch)
        if message.learner_epoch != self.epoch or not same_instance:
            self._adoptions.clear()  # another learner: its pace is its own
        self._adoptions.append((time.monotonic(), weights.order[1]))
        self.epoch, self.version = weights.order
        self._held_from = weights.nonce
        self._refusing_since, self._refusals = None, 0
        self.bus.stamp.acting_for(*weights.order)
        self.counts["weights_adopted"] += 1
        if weights.published_at is not None:
            self._latency_ms.append(1000.0 * (time.time() - weights.published_at))

    def _resync(self) -> bool:
        """Every frame refused for RESYNC_AFTER_S: take the learner's answer to a query as its current weights."""
        log.warning("every weights frame refused for %.0f s (%d of them; holding epoch %d version %d): asking the "
                    "learner for its current weights", time.monotonic() - (self._refusing_since or 0.0),
                    self._refusals, self.epoch, self.version)
        self._refusing_since, self._refusals = None, 0
        self.counts["resyncs"] += 1
        for weights in self._decoded(self.bus.get(self.bus.keys.weights_latest, timeout_s=2.0)[-1:]):
            try:
                if self._acceptable(weights, resync=True):
                    self._take(weights)
                    return True
            except Rejected as err:
                self.bus.rejects.record(err.reason, "weights", err.detail)
        return False
