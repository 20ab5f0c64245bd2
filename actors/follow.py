"""Following the learner: adopting its newest weights and noticing whether it is there. The actor process and the
evaluator both follow the learner the same way.

Weights. A weights frame is adopted only when its digest matches (`bus.codec`), it fits the network (the schema
made from the follower's parameter template), and its (learner epoch, policy version) is strictly newer than the
weights held; a replayed older frame is refused as stale and one equal to the weights held is ignored (counted as
repeated). The one exception is a restarted learner: once the learner's liveliness token has gone and come back,
weights of another epoch are adopted even if that epoch is lower (a run directory started afresh). Who sent them
is what the key says: only the learner may publish there. Until the first weights arrive, the follower also asks
the learner's queryable every WEIGHTS_QUERY_EVERY_S (the cached broadcast usually arrives first).

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
from impulse.bus.keys import LEARNER
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


class FollowEvents(NamedTuple):
    """What one `LearnerFollower.poll` saw."""

    adopted: bool
    """New weights were adopted."""
    new_epoch: bool
    """... and they are of another learner epoch than the weights held before (a restarted learner)."""
    learner_back: bool
    """The learner's liveliness token came back after it had gone (a broken link, a restarted router or learner)."""


class LearnerPresence:
    """Whether the learner is there (its liveliness token) and whether it has finished the run (its latest status
    says so and its token is gone: see the module docstring), for every process that follows the learner, with or
    without its weights (the recorder). A learner on several hosts is its leader, named `learner`; the tokens and
    statuses of its other processes are not the learner's."""

    def __init__(self, bus: Bus):
        self.bus = bus
        self._tokens = bus.watch_alive(bus.keys.alive_pattern(LEARNER))
        self._statuses = bus.inbox(bus.keys.status_pattern(LEARNER), 4, drop_oldest=True)
        self.present = False
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
            if self.bus.keys.parse_alive(key)[1] != LEARNER:
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
    as one process sees them (see the module docstring). Refused frames are counted by the bus's reject counter."""

    def __init__(self, bus: Bus, params_template: Any):
        self.bus = bus
        self._template = params_template
        self._schema = weights_schema(params_template)
        keys = bus.keys
        self._weights = bus.inbox(keys.weights_policy, 1, drop_oldest=True, latest=True)
        self.learner = LearnerPresence(bus)
        self.params: Any = None
        self.epoch = -1
        self.version = -1
        self.counts = {"weights_adopted": 0, "weights_by_query": 0, "weights_repeated": 0}
        self._returned = False  # the learner came back: weights of another epoch may be adopted
        self._last_query = -float("inf")
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
        """Note the learner's comings and goings and its word, then adopt the newest weights that arrived (asking
        for them while there are none yet)."""
        learner_back = self.learner.poll()
        if learner_back:
            self._returned = True
        payloads = [received.payload for received in self._weights.poll()]
        queried = False
        if self.params is None and time.monotonic() - self._last_query >= WEIGHTS_QUERY_EVERY_S:
            self._last_query = time.monotonic()
            answers = self.bus.get(self.bus.keys.weights_latest, timeout_s=1.0)
            queried = bool(answers) and not payloads
            payloads = answers[-1:] + payloads
        adopted = new_epoch = False
        for payload in payloads[-1:]:
            first, epoch_before = self.params is None, self.epoch
            try:
                adopted = self._adopt(decode_weights(payload, self.bus.keys.run))
            except Rejected as err:
                self.bus.rejects.record(err.reason, "weights", err.detail)
                continue
            new_epoch = adopted and epoch_before >= 0 and self.epoch != epoch_before
            if adopted and queried:
                self.counts["weights_by_query"] += 1
            if adopted and first:
                log.info("adopted the learner's current weights %s: version %d, epoch %d",
                         "by query" if queried else "from its cached broadcast", self.version, self.epoch)
        return FollowEvents(adopted, new_epoch, learner_back)

    def _adopt(self, weights: Weights) -> bool:
        """Adopt checked weights if they are newer than those held; False for a repeat. Raises `Rejected`."""
        message = weights.message
        check(message, self._schema)
        held, offered = (self.epoch, self.version), weights.order
        if offered == held:
            self.counts["weights_repeated"] += 1  # the cached broadcast again (a reconnection), or a copy
            return False
        restarted = self._returned and message.learner_epoch != self.epoch
        if offered < held and not restarted:
            raise Rejected("stale", f"weights of epoch {offered[0]} version {offered[1]}, older than the epoch "
                           f"{held[0]} version {held[1]} held (a replay?)")
        self._returned = False
        self.params = jax.device_put(tree_from_arrays(message.arrays, self._template))
        if message.learner_epoch != self.epoch and self.epoch >= 0:
            log.info("the learner restarted (epoch %d -> %d)", self.epoch, message.learner_epoch)
        if message.learner_epoch != self.epoch:
            self._adoptions.clear()  # another learner: its pace is its own
        self._adoptions.append((time.monotonic(), offered[1]))
        self.epoch, self.version = offered
        self.bus.stamp.acting_for(*offered)
        self.counts["weights_adopted"] += 1
        if weights.published_at is not None:
            self._latency_ms.append(1000.0 * (time.time() - weights.published_at))
        return True
