"""Following the learner over real zenoh sessions on loopback (a hub and three sessions in this process): weights
are adopted only from the learner instance whose token the follower follows, every frame that reaches the
follower is checked or counted, a second instance is reported, a restarted learner is followed whatever its
versions, and a follower that refuses every frame for a while re-syncs by query."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from impulse.actors import follow
from impulse.actors.follow import LearnerFollower
from impulse.actors.wire import weights_hash
from impulse.bus.config import BusConfig
from impulse.bus.keys import ACTOR, LEARNER
from impulse.bus.session import Bus, Hub
from impulse.bus.weights import encode_weights

pytestmark = pytest.mark.heavy

TEMPLATE = {"w": np.zeros(3, np.float32)}


@pytest.fixture
def hub() -> Iterator[BusConfig]:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        config = BusConfig(hub=f"tcp/127.0.0.1:{sock.getsockname()[1]}")
    with Hub(config):
        yield config


class FakeLearner:
    """A learner instance as followers see it: an instance token, a cached weights broadcast and a queryable."""

    def __init__(self, hub: BusConfig, run: str, nonce: str) -> None:
        self.bus = Bus(hub, run, LEARNER, LEARNER)
        self.bus.stamp.nonce = nonce
        self.bus.declare_token(self.bus.keys.learner_instance(nonce))
        self.publisher = self.bus.latest_publisher(self.bus.keys.weights_policy)
        self.queries = self.bus.queryable(self.bus.keys.weights_latest, 8)
        self.current = b""
        self._answering = threading.Thread(target=self._answer, daemon=True)
        self._answering.start()

    def _answer(self) -> None:
        """Answer weights queries with the newest frame published, as the learner's cycle does."""
        while not self.bus.closed:
            query = self.queries.wait(0.05)
            if query is not None and self.current:
                query.reply(self.current)

    def frame(self, version: int, epoch: int = 1, value: float = 0.0) -> bytes:
        self.bus.stamp.acting_for(epoch, version)
        return encode_weights(self.bus.stamp, {"w": np.full(3, value, np.float32)}, weights_hash(TEMPLATE))

    def publish(self, version: int, epoch: int = 1) -> bytes:
        self.current = self.frame(version, epoch, float(version))
        self.publisher.put(self.current)
        return self.current


def until(condition: Callable[[], bool], what: str, poll: Callable[[], object], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        poll()
        time.sleep(0.05)


def test_followers_adopt_only_their_learner_instance_and_count_every_frame(hub: BusConfig) -> None:
    run = "follow"
    learner = FakeLearner(hub, run, "aaaa")
    with Bus(hub, run, ACTOR, "a0") as actor_bus, Bus(hub, run, "operator", "stray") as stray:
        follower = LearnerFollower(actor_bus, TEMPLATE)
        rejected = actor_bus.rejects.counts
        learner.publish(3)
        until(lambda: follower.version == 3, "the first weights", follower.poll)
        assert follower.followed == "aaaa" and float(follower.params["w"][0]) == 3.0

        # A stray frame: intact digest, the right network, a far higher version, another learner's nonce.
        impostor = FakeLearner.__new__(FakeLearner)
        impostor.bus = stray
        stray.stamp.nonce = "bbbb"
        foreign = impostor.frame(10**6)
        weights_key = stray.publisher(stray.keys.weights_policy)
        assert stray.wait_matching(weights_key, 10)
        weights_key.put(foreign)
        stray.stamp.nonce = ""
        weights_key.put(impostor.frame(10**6 + 1))  # one naming no instance at all
        until(lambda: rejected().get("foreign_learner", 0) == 2, "both stray frames refused", follower.poll)
        assert follower.version == 3

        # Five replays and five bit flips between two polls: each one checked and counted.
        old = learner.current
        learner.publish(4)
        until(lambda: follower.version == 4, "version 4", follower.poll)
        for _ in range(5):
            weights_key.put(old)
        flipped = bytearray(learner.current)
        flipped[-40] ^= 0x01
        for _ in range(5):
            weights_key.put(bytes(flipped))
        until(lambda: rejected().get("stale", 0) + follower.counts["dropped_weights_overwritten"] >= 5
              and rejected().get("digest", 0) >= 5 - follower.counts["dropped_weights_overwritten"],
              "every replay and flip counted", follower.poll)
        time.sleep(0.3)
        follower.poll()
        counted = rejected().get("stale", 0) + rejected().get("digest", 0) + follower.counts[
            "dropped_weights_overwritten"]
        assert counted == 10, (rejected(), follower.counts)
        assert follower.version == 4

        # A second instance on the bus is reported; once the first is gone, the second is followed from its
        # own (lower) versions on: a restarted learner.
        second = FakeLearner(hub, run, "cccc")
        until(lambda: follower.counts["learners_seen"] == 2, "the second instance", follower.poll)
        second.publish(0, epoch=2)
        until(lambda: rejected().get("foreign_learner", 0) >= 3, "the second's weights refused while the first lives",
              follower.poll)
        learner.bus.close()
        until(lambda: follower.followed == "cccc", "the second followed", follower.poll)
        second.publish(1, epoch=2)
        until(lambda: (follower.epoch, follower.version) == (2, 1), "the restarted learner's weights", follower.poll)
        second.bus.close()


def test_a_follower_that_refuses_everything_resyncs_by_query(hub: BusConfig, monkeypatch) -> None:
    monkeypatch.setattr(follow, "RESYNC_AFTER_S", 1.0)
    run = "resync"
    learner = FakeLearner(hub, run, "dddd")
    with Bus(hub, run, ACTOR, "a0") as actor_bus:
        follower = LearnerFollower(actor_bus, TEMPLATE)
        learner.publish(50)  # a bug: the learner published a version it is not at
        until(lambda: follower.version == 50, "version 50", follower.poll)
        for version in (5, 6, 7, 8):  # ... and goes on from its real one: each frame refused as stale
            learner.publish(version)
            time.sleep(0.2)
            follower.poll()

        deadline = time.monotonic() + 10
        while follower.version != 8:
            assert time.monotonic() < deadline, (follower.version, actor_bus.rejects.counts())
            learner.publish(8)
            follower.poll()
            time.sleep(0.2)
        assert follower.counts["resyncs"] == 1 and actor_bus.rejects.counts().get("stale", 0) >= 3
    learner.bus.close()
