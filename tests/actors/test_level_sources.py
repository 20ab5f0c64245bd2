"""An actor waiting for levels from a curriculum service that does not answer (not started, or stopping) waits
while its `while_waiting` says so, and gives up with None as soon as it says stop: a stop signal must not leave an
actor blocked in a cycle (a real Zenoh hub and session in this process; no service)."""

from __future__ import annotations

import socket

from impulse.actors.levels import CurriculumLevels
from impulse.bus.config import BusConfig
from impulse.bus.session import Bus, Hub
from impulse.curriculum.wire import level_batch_template
from impulse.engine.physics.sizes import SceneSizes


def free_endpoint() -> str:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"


def test_waiting_for_levels_ends_when_asked_to_stop() -> None:
    config = BusConfig(hub=free_endpoint())
    calls = []

    def keep_waiting() -> bool:
        calls.append(1)
        return len(calls) < 3

    with Hub(config), Bus(config, "no-service", "actor", "0") as bus:
        source = CurriculumLevels(bus, level_batch_template(SceneSizes(), 4), "plr", timeout_s=0.2)
        assert source.next_batch(None, keep_waiting) is None
    assert len(calls) == 3, "it asked before every further wait and stopped at the first no"
    assert source.waiting
