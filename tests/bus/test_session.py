"""Sessions over real zenoh on loopback: hub and peers in separate processes, crashes, restarts, start order.

Every subprocess is told to stop at the end and must exit by itself within a few seconds (zenoh's exit hang).
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zenoh

from impulse.bus.codec import Kind, decode, encode
from impulse.bus.config import BusConfig
from impulse.bus.inbox import AliveWatcher
from impulse.bus.session import PEER_LISTEN, Bus, Hub, zenoh_config
from tests.support.bus_procs import BusProcess

pytestmark = pytest.mark.heavy

STOP_WITHIN_S = 5.0


def free_endpoint() -> str:
    """A loopback TCP endpoint on a port that is free now (a connect endpoint cannot use port 0)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{sock.getsockname()[1]}"


@pytest.fixture
def spawn() -> Iterator[Callable[..., BusProcess]]:
    """Start bus_procs.py processes; at the end every one still running must stop by itself."""
    procs: list[BusProcess] = []

    def start(*args: str) -> BusProcess:
        proc = BusProcess(*args)
        procs.append(proc)
        return proc

    yield start
    try:
        for proc in procs:
            if proc.proc.poll() is None:
                assert proc.stop(STOP_WITHIN_S) == 0, "\n".join(proc.output)
    finally:
        for proc in procs:
            proc.cleanup()


@pytest.fixture(scope="module")
def hub() -> Iterator[str]:
    """A hub process shared by the tests of this module (each test uses its own run id)."""
    endpoint = free_endpoint()
    proc = BusProcess("hub", endpoint)
    try:
        proc.expect("ready")
        yield endpoint
        assert proc.stop(STOP_WITHIN_S) == 0
        proc.expect("closed", timeout_s=1)
    finally:
        proc.cleanup()


@pytest.fixture(scope="module")
def local_hub() -> Iterator[BusConfig]:
    """A hub inside the test process, for tests that need no other process."""
    config = BusConfig(hub=free_endpoint())
    with Hub(config):
        yield config


def stop_cleanly(proc: BusProcess) -> None:
    assert proc.stop(STOP_WITHIN_S) == 0, "\n".join(proc.output)
    proc.expect("closed", timeout_s=1)


def setting(conf: zenoh.Config, key: str) -> object:
    """A zenoh config value as Python data (`get_json` returns JSON text)."""
    return json.loads(conf.get_json(key))


def next_change(watcher: AliveWatcher, key: str, timeout_s: float) -> bool:
    """The next liveliness change of `key` (True: appeared, False: gone); fails after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        change = watcher.wait(left)
        if change is not None and change[0] == key:
            return change[1]
    raise AssertionError(f"no liveliness change of {key} within {timeout_s} s")


# ---------------------------------------------------------------------------------------------- configuration


def test_bus_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="endpoint"):
        BusConfig(hub="127.0.0.1:7447")
    with pytest.raises(ValueError, match="list of endpoints"):
        BusConfig(connect="tcp/10.0.0.1:7447")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="endpoint"):
        BusConfig(connect=("tcp/10.0.0.1:7447", "nonsense"))
    with pytest.raises(ValueError, match="shm_pool_mib"):
        BusConfig(shm_pool_mib=0)
    with pytest.raises(ValueError, match="lease_ms"):
        BusConfig(lease_ms=-5)
    with pytest.raises(ValueError, match="query_timeout_s"):
        BusConfig(query_timeout_s=0)
    with pytest.raises(ValueError, match="shared_memory"):
        BusConfig(shared_memory="yes")  # type: ignore[arg-type]
    assert BusConfig(connect=["tcp/10.0.0.1:7447"]).connect == ("tcp/10.0.0.1:7447",)  # type: ignore[arg-type]


def test_zenoh_config_peer_hub_and_routers() -> None:
    config = BusConfig(hub="tcp/127.0.0.1:7000", shm_pool_mib=32, lease_ms=2000, block_timeout_ms=9000)
    peer = zenoh_config(config, listen=False)
    assert setting(peer, "mode") == "peer"
    assert setting(peer, "scouting/multicast/enabled") is False
    assert setting(peer, "timestamping/enabled") is True
    assert setting(peer, "listen/endpoints") == [PEER_LISTEN]
    assert setting(peer, "connect/endpoints") == ["tcp/127.0.0.1:7000"]
    assert setting(peer, "connect/timeout_ms") == -1
    assert setting(peer, "connect/exit_on_failure") is False
    retry = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2.0}
    assert setting(peer, "connect/retry") == retry
    assert setting(peer, "transport/shared_memory/transport_optimization/pool_size") == 32 << 20
    assert setting(peer, "transport/link/tx/lease") == 2000
    assert setting(peer, "transport/link/tx/queue/congestion_control/block/wait_before_close") == 9_000_000
    hub_side = zenoh_config(config, listen=True)
    assert setting(hub_side, "listen/endpoints") == ["tcp/127.0.0.1:7000"]
    assert setting(hub_side, "connect/endpoints") == []
    routers = zenoh_config(BusConfig(connect=("tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447")), listen=False)
    assert setting(routers, "connect/endpoints") == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    no_shm = zenoh_config(BusConfig(shared_memory=False), listen=False)
    assert setting(no_shm, "transport/shared_memory/enabled") is False


def test_bus_refuses_bad_names(local_hub: BusConfig) -> None:
    with pytest.raises(ValueError, match="role"):
        Bus(local_hub, "run", "act or", "0")
    with pytest.raises(ValueError, match="run id"):
        Bus(local_hub, "run/1", "actor", "0")


# ------------------------------------------------------------------------------------------- in one process


def test_first_put_after_wait_matching_is_delivered(local_hub: BusConfig) -> None:
    """`matching_status` is an always-truthy object; testing it instead of `.matching` lost most first puts."""
    with Bus(local_hub, "first-put", "learner", "0") as receiver:
        inbox = receiver.inbox(receiver.keys.traj_all, 16)
        for trial in range(3):
            with Bus(local_hub, "first-put", "actor", f"a{trial}") as sender:
                publisher = sender.publisher(sender.keys.traj(f"a{trial}"))
                assert Bus.wait_matching(publisher, 2.0)
                publisher.put(encode(Kind.TRAJECTORY, {"x": np.arange(3)}, run="first-put", seq=trial))
                received = inbox.wait(2.0)
                assert received is not None, f"trial {trial}: first put lost"
                assert received.key == sender.keys.traj(f"a{trial}")
                assert decode(received.payload, run="first-put").seq == trial


def test_inbox_fifo_attachment_and_timeout(local_hub: BusConfig) -> None:
    with Bus(local_hub, "fifo", "learner", "0") as receiver, Bus(local_hub, "fifo", "actor", "a0") as sender:
        inbox = receiver.inbox(receiver.keys.traj_all, 16)
        publisher = sender.publisher(sender.keys.traj("a0"))
        assert Bus.wait_matching(publisher, 2.0)
        for seq in range(5):
            publisher.put(encode(Kind.TRAJECTORY, {}, run="fifo", seq=seq), attachment=seq.to_bytes(8, "little"))
        got: list[int] = []
        deadline = time.monotonic() + 3
        while len(got) < 5 and time.monotonic() < deadline:
            for received in inbox.poll(max_items=2):
                assert received.attachment is not None
                assert int.from_bytes(received.attachment, "little") == decode(received.payload, run="fifo").seq
                got.append(decode(received.payload, run="fifo").seq)
            time.sleep(0.01)
        assert got == [0, 1, 2, 3, 4]
        started = time.monotonic()
        assert inbox.wait(0.2) is None
        assert time.monotonic() - started >= 0.2


def test_inbox_drop_oldest_keeps_the_newest(local_hub: BusConfig) -> None:
    with Bus(local_hub, "ring", "actor", "a0") as receiver, Bus(local_hub, "ring", "learner", "0") as sender:
        inbox = receiver.inbox(receiver.keys.credit("a0"), 3, drop_oldest=True)
        publisher = sender.publisher(sender.keys.credit("a0"))
        assert Bus.wait_matching(publisher, 2.0)
        for seq in range(10):
            publisher.put(encode(Kind.CREDIT, {}, run="ring", seq=seq))
        time.sleep(0.5)
        assert [decode(r.payload, run="ring").seq for r in inbox.poll()] == [7, 8, 9]


def test_query_error_reply_and_nobody_answering(local_hub: BusConfig) -> None:
    with Bus(local_hub, "qerr", "curriculum", "0") as server, Bus(local_hub, "qerr", "actor", "a0") as client:
        queries = server.queryable(server.keys.levels_sample, 4)
        assert client.wait_queryable(client.keys.levels_sample, 2.0)
        assert not client.wait_queryable(client.keys.weights_latest, 0.1)
        result: dict[str, list[bytes]] = {}
        asking = threading.Thread(target=lambda: result.update(got=client.get(client.keys.levels_sample, timeout_s=5)))
        started = time.monotonic()
        asking.start()
        query = queries.wait(3.0)
        assert query is not None
        query.reply_error("no levels yet")
        with pytest.raises(RuntimeError, match="already answered"):
            query.reply(b"late")
        asking.join()
        assert result["got"] == []
        assert time.monotonic() - started < 4, "an answered query must not wait for the timeout"
        assert client.get(client.keys.weights_latest, timeout_s=0.3) == []


def test_a_flood_of_queries_is_dropped_and_counted_without_stalling_the_session(local_hub: BusConfig) -> None:
    """More queries than a queryable holds, while its owner is busy: the newest are dropped and counted, the asker
    of a dropped one gets no reply, and the session goes on receiving everything else (a blocking channel would
    hold zenoh's receive thread until the owner drained it)."""
    with Bus(local_hub, "flood", "curriculum", "0") as server, Bus(local_hub, "flood", "actor", "a0") as client:
        queries = server.queryable(server.keys.curriculum_knobs, 2)
        inbox = server.inbox(server.keys.credit("a0"), 4)
        assert client.wait_queryable(client.keys.curriculum_knobs, 2.0)
        credit = client.publisher(client.keys.credit("a0"))
        assert client.wait_matching(credit, 2.0)
        asked = [client.session.get(client.keys.curriculum_knobs, payload=str(i).encode(), timeout=5)
                 for i in range(6)]  # sent at once; their replies are read below
        deadline = time.monotonic() + 3
        while queries.dropped < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert queries.dropped == 4
        credit.put(b"after the flood")
        received = inbox.wait(3.0)
        assert received is not None and received.payload == b"after the flood"
        held = queries.poll()
        assert [query.payload for query in held] == [b"0", b"1"]
        for query in held:
            query.reply(b"answer to " + query.payload)
        started = time.monotonic()
        answers = [[reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None] for replies in asked]
        assert answers == [[b"answer to 0"], [b"answer to 1"], [], [], [], []]
        assert time.monotonic() - started < 4, "a dropped query must end its asker's get before the timeout"


def test_close_is_idempotent_and_withdraws_the_token(local_hub: BusConfig) -> None:
    with Bus(local_hub, "close", "learner", "0") as learner:
        watcher = learner.watch_alive(learner.keys.alive_pattern("actor"))
        bus = Bus(local_hub, "close", "actor", "a7")
        bus.inbox(bus.keys.credit("a7"), 2, latest=True)
        bus.publisher(bus.keys.traj("a7"))
        bus.queryable(bus.keys.weights_latest, 2)
        bus.watch_alive(bus.keys.alive_pattern())
        assert next_change(watcher, bus.alive_key, 3) is True
        assert learner.alive_now(learner.keys.alive_pattern("actor")) == [bus.alive_key]
        bus.close()
        bus.close()
        assert bus.closed and bus.session.is_closed()
        assert next_change(watcher, bus.alive_key, 3) is False
        assert learner.alive_now(learner.keys.alive_pattern("actor"), timeout_s=0.5) == []
        with pytest.raises(RuntimeError, match="closed"):
            bus.inbox(bus.keys.credit("a7"), 2, latest=True)


def test_wait_matching_times_out_without_subscriber(local_hub: BusConfig) -> None:
    with Bus(local_hub, "lonely", "actor", "a0") as bus:
        assert not Bus.wait_matching(bus.publisher(bus.keys.traj("a0")), 0.2)


# ------------------------------------------------------------------------------------------ across processes


def test_hub_and_two_peers_exchange_both_ways(hub: str, spawn: Callable[..., BusProcess]) -> None:
    a = spawn("peer", hub, "pair", "a", "b")
    b = spawn("peer", hub, "pair", "b", "a")
    a.expect("linked", other="b")
    b.expect("linked", other="a")
    stop_cleanly(a)
    stop_cleanly(b)


def test_latest_publisher_serves_a_late_joiner(hub: str, spawn: Callable[..., BusProcess]) -> None:
    learner = spawn("latest", hub, "late")
    learner.expect("published", version=3)
    with Bus(BusConfig(hub=hub), "late", "actor", "a0") as bus:
        inbox = bus.inbox(bus.keys.weights_policy, 8, latest=True)
        received = inbox.wait(5.0)
        assert received is not None, "the late joiner got no cached weights"
        message = decode(received.payload, run="late", kinds=Kind.WEIGHTS)
        assert message.policy_version == 3
        np.testing.assert_array_equal(message.arrays["w"], np.full((4, 3), 3, np.float32))
        time.sleep(0.3)
        assert inbox.poll() == [], "only the newest weights are cached"
    stop_cleanly(learner)


def test_queryable_get_round_trip(hub: str, spawn: Callable[..., BusProcess]) -> None:
    curriculum = spawn("levels", hub, "query")
    curriculum.expect("ready")
    with Bus(BusConfig(hub=hub), "query", "actor", "a3") as bus:
        replies = bus.get(bus.keys.levels_sample, payload=b"hello", parameters="n=5;actor=a3", timeout_s=5)
        assert len(replies) == 1
        message = decode(replies[0], run="query", kinds=Kind.LEVELS)
        np.testing.assert_array_equal(message.arrays["level_id"], np.arange(5))
        assert message.meta == {"asked_by": "a3", "note": "hello"}
    stop_cleanly(curriculum)


def test_liveliness_sees_sigkill_and_restart(hub: str, spawn: Callable[..., BusProcess]) -> None:
    with Bus(BusConfig(hub=hub), "alive", "learner", "0") as learner:
        watcher = learner.watch_alive(learner.keys.alive_pattern("actor"))
        key = learner.keys.alive("actor", "a0")
        actor = spawn("alive", hub, "alive", "a0")
        assert next_change(watcher, key, 10) is True
        assert learner.alive_now(learner.keys.alive_pattern("actor")) == [key]
        assert learner.keys.parse_alive(key) == ("actor", "a0")
        killed = time.monotonic()
        actor.kill()
        assert next_change(watcher, key, 3) is False
        assert time.monotonic() - killed < 2, "a SIGKILLed peer is noticed at once (its sockets close)"
        restarted = spawn("alive", hub, "alive", "a0")
        assert next_change(watcher, key, 10) is True
        stop_cleanly(restarted)
        assert next_change(watcher, key, 3) is False


def test_peer_started_before_the_hub_connects_when_it_starts(spawn: Callable[..., BusProcess]) -> None:
    endpoint = free_endpoint()
    early = spawn("peer", endpoint, "order", "early", "late")
    early.expect("ready")
    time.sleep(1.0)
    hub = spawn("hub", endpoint)
    hub.expect("ready")
    late = spawn("peer", endpoint, "order", "late", "early")
    early.expect("linked", other="late")
    late.expect("linked", other="early")
    for proc in (early, late, hub):
        stop_cleanly(proc)


def test_peer_reconnects_after_the_hub_restarts(spawn: Callable[..., BusProcess]) -> None:
    """Only a peer reconnected to the new hub can be introduced to a peer that joins after the restart."""
    endpoint = free_endpoint()
    hub = spawn("hub", endpoint)
    hub.expect("ready")
    old = spawn("peer", endpoint, "restart", "old", "first,second")
    first = spawn("peer", endpoint, "restart", "first", "old")
    old.expect("linked", other="first")
    hub.kill()
    new_hub = spawn("hub", endpoint)
    new_hub.expect("ready")
    second = spawn("peer", endpoint, "restart", "second", "old")
    second.expect("linked", other="old")
    old.expect("linked", other="second")
    for proc in (old, first, second, new_hub):
        stop_cleanly(proc)
