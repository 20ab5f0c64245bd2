"""Zenoh sessions: one configuration for every process, and a `Bus` that remembers and closes what it declares.

Topology on one machine: a hub process (`run_hub`) listens on `BusConfig.hub` (loopback); learner, curriculum and
actors are peers that connect to it. The hub is a process of its own so that any of them can restart without
breaking the others' connections. Several machines: `connect` lists router endpoints instead.

What the session handling relies on (zenoh's behaviour on loopback, measured and listed in docs/distributed.md,
"What zenoh does"): peers that connect to the hub open direct links by gossip and deliver only over them, so `Bus()`
returns once its links have settled and a publisher waits for `wait_matching` (whose `.matching` flag, not the
always-truthy status object, says a subscriber is there) before its first put; a `get` finds only queryables
already declared to it (`wait_queryable`); connect endpoints are retried forever, so a peer started before the hub,
or whose hub restarts, links up by itself; a peer killed with SIGKILL is seen gone at once by liveliness. Protocols
still tolerate losing a message to a peer that joined a moment ago (re-granted credits, retried queries).
Subscriptions and queryables feed `Mailbox` callbacks (`bus.inbox`, `bus.queryable`); a session holding callbacks
must be closed explicitly or its process does not exit, which `Bus.close` does, undeclaring every entity (advanced
subscribers first) before it closes the session.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

import zenoh
import zenoh.ext

from impulse.bus.config import BusConfig, check_positive
from impulse.bus.inbox import AliveWatcher, Inbox, Mailbox, QueryInbox
from impulse.bus.keys import Keys, check_name, check_role
from impulse.bus.rejects import RejectCounter
from impulse.bus.router import client_security
from impulse.bus.stamp import Stamp

log = logging.getLogger("impulse.bus")

PEER_LISTEN = "tcp/127.0.0.1:0"
"""Where a non-hub peer listens (any free port, loopback only) so the hub's gossip can link peers directly."""
CONNECT_RETRY_INIT_MS = 250
CONNECT_RETRY_MAX_MS = 1000
"""Back-off of connect retries: a peer finds a (re)started hub within about a second."""
LINK_SETTLE_QUIET_S = 0.05
LINK_SETTLE_MAX_S = 1.0
"""`Bus()` returns once its set of directly linked peers has not changed for LINK_SETTLE_QUIET_S (at most
LINK_SETTLE_MAX_S): peers only deliver over direct links, which gossip opens just after `zenoh.open` returns."""
LINK_SETTLE_POLL_S = 0.002
ALIVE_CHANNEL_SIZE = 1024
MATCHING_POLL_S = 0.01


def zenoh_config(config: BusConfig, *, listen: bool, role: str = "") -> zenoh.Config:
    """The zenoh configuration of a hub (`listen=True`: listens on `config.hub`), of a peer (connects to it), or,
    when `config.connect` lists routers, of a client of those routers with `role`'s credentials.

    Peer mode, multicast scouting off (nothing leaves loopback unless configured), gossip on (peers link
    directly), timestamping on (the advanced publisher/subscriber need it), connect endpoints retried forever.
    A client has no direct links: everything passes the router, which enforces its access control.
    """
    client = bool(config.connect) and not listen
    settings: dict[str, Any] = {
        "mode": "client" if client else "peer",
        "scouting/multicast/enabled": False,
        "timestamping/enabled": True,
        "listen/endpoints": [config.hub] if listen else [PEER_LISTEN],
        "connect/endpoints": list(config.connect) if listen or config.connect else [config.hub],
        "connect/timeout_ms": -1,
        "connect/exit_on_failure": False,
        "connect/retry": {
            "period_init_ms": CONNECT_RETRY_INIT_MS,
            "period_max_ms": CONNECT_RETRY_MAX_MS,
            "period_increase_factor": 2.0,
        },
        "transport/shared_memory/enabled": config.shared_memory,
        "transport/shared_memory/transport_optimization/pool_size": config.shm_pool_mib << 20,
        "transport/link/tx/lease": config.lease_ms,
        "transport/link/tx/queue/congestion_control/block/wait_before_close": config.block_timeout_ms * 1000,
    }
    if client:
        del settings["listen/endpoints"]
        settings.update(client_security(config.credentials, role))
    conf = zenoh.Config()
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


class Bus:
    """One process's zenoh session, its liveliness token, and every entity declared through it.

    `role` is the name of one of the run's roles (`bus.roles`; the launcher, command-line tools and watchers are
    operators); the process publishes under that role's prefix and, across machines, presents that role's
    credentials.

    `close()` (or leaving the `with` block) undeclares them all, advanced subscribers first, then closes the
    session; a session left open keeps the process from exiting.
    """

    def __init__(self, config: BusConfig, run: str, role: str, ident: str, *, listen: bool = False) -> None:
        self.config = config
        self.keys = Keys(run)
        self.stamp = Stamp(run)
        """What this process's frames say about it (`bus.stamp`)."""
        self.role = check_role(role)
        self.ident = check_name(ident, "id")
        self.rejects = RejectCounter()
        self._advanced_subscribers: list[Any] = []
        self._entities: list[Any] = []
        self._closed = False
        conf = zenoh_config(config, listen=listen, role=self.role)
        if config.connect and not listen:
            log.info("connecting to %s as %s/%s (waits until a router answers)", ", ".join(config.connect),
                     self.role, self.ident)
        self.session = zenoh.open(conf)
        try:
            self._settle_links()
            self.alive_key = self.keys.alive(self.role, self.ident)
            self._remember(self.session.liveliness().declare_token(self.alive_key))
        except BaseException:
            self.session.close()
            raise

    def linked_peers(self) -> set[str]:
        """Zenoh ids of the sessions this one has a direct link to (the hub and, through gossip, the others)."""
        return {str(zid) for zid in self.session.info.peers_zid()}

    def _settle_links(self) -> None:
        deadline = time.monotonic() + LINK_SETTLE_MAX_S
        peers = self.linked_peers()
        quiet_since = time.monotonic()
        while time.monotonic() < deadline and time.monotonic() - quiet_since < LINK_SETTLE_QUIET_S:
            time.sleep(LINK_SETTLE_POLL_S)
            now = self.linked_peers()
            if now != peers:
                peers, quiet_since = now, time.monotonic()

    def __enter__(self) -> Bus:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"the bus of {self.role}/{self.ident} is closed")

    def _remember(self, entity: Any) -> Any:
        self._entities.append(entity)
        return entity

    def publisher(
        self,
        key: str,
        *,
        block: bool = True,
        priority: zenoh.Priority = zenoh.Priority.DATA,
        express: bool = False,
    ) -> zenoh.Publisher:
        """A publisher on `key`. `block=True` waits (up to block_timeout_ms) when the receiver's queue is full
        (trajectories, weights, levels); `block=False` drops instead (metrics)."""
        self._check_open()
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        return self._remember(
            self.session.declare_publisher(
                key,
                encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
                congestion_control=congestion,
                priority=priority,
                express=express,
            )
        )

    def latest_publisher(self, key: str) -> zenoh.ext.AdvancedPublisher:
        """A publisher that keeps its newest sample, so an `inbox(key, latest=True)` declared later still gets it
        (the weights broadcast)."""
        self._check_open()
        return self._remember(
            zenoh.ext.declare_advanced_publisher(
                self.session,
                key,
                encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.DATA_HIGH,
                cache=zenoh.ext.CacheConfig(max_samples=1),
                publisher_detection=True,
            )
        )

    def inbox(self, key: str, capacity: int, *, drop_oldest: bool = False, latest: bool = False) -> Inbox:
        """Subscribe to `key` into a mailbox of `capacity` samples, drained with `Inbox.poll`/`wait`.

        A full mailbox drops the newest sample (the default: what waits is kept in order) or, with `drop_oldest`,
        the oldest; either way it counts the drop (`Inbox.dropped`). `latest=True` also fetches the newest sample
        cached by a `latest_publisher`, even one published before this call.
        """
        self._check_open()
        check_positive("inbox capacity", capacity, int)
        mailbox = Mailbox(capacity, drop_oldest)
        handler = zenoh.handlers.Callback(mailbox)
        if not latest:
            return Inbox(self._remember(self.session.declare_subscriber(key, handler)), key, mailbox)
        history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1)
        subscriber = zenoh.ext.declare_advanced_subscriber(self.session, key, handler, history=history)
        self._advanced_subscribers.append(subscriber)
        return Inbox(subscriber, key, mailbox)

    def queryable(self, key: str, capacity: int) -> QueryInbox:
        """Serve queries on `key`; up to `capacity` of them wait until `QueryInbox.poll` hands them out, and more
        are dropped and counted (`QueryInbox.dropped`)."""
        self._check_open()
        check_positive("queryable capacity", capacity, int)
        mailbox = Mailbox(capacity, drop_oldest=False)
        queryable = self.session.declare_queryable(key, zenoh.handlers.Callback(mailbox))
        return QueryInbox(self._remember(queryable), key, mailbox)

    def get(
        self, key: str, *, payload: bytes | None = None, parameters: str = "", timeout_s: float | None = None
    ) -> list[bytes]:
        """Ask the queryables on `key` (with `parameters` like "n=64;actor=a0") and return the successful
        replies' payloads; empty if nobody answered within `timeout_s` (default: config.query_timeout_s)."""
        selector = f"{key}?{parameters}" if parameters else key
        timeout = self.config.query_timeout_s if timeout_s is None else timeout_s
        replies = self.session.get(selector, payload=payload, timeout=timeout)
        return [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]

    def wait_queryable(self, key: str, timeout_s: float) -> bool:
        """Wait until some queryable serves `key` (a `get` sent before that finds nobody); False on timeout."""
        querier = self.session.declare_querier(key)
        try:
            return self.wait_matching(querier, timeout_s)
        finally:
            querier.undeclare()

    def declare_token(self, key: str) -> None:
        """Declare one more liveliness token (beside this process's own `alive_key`), kept until `close`."""
        self._check_open()
        self._remember(self.session.liveliness().declare_token(key))

    def watch_alive(self, pattern: str) -> AliveWatcher:
        """Watch liveliness tokens under `pattern` (see `Keys.alive_pattern`); tokens alive now come first."""
        self._check_open()
        channel = zenoh.handlers.RingChannel(ALIVE_CHANNEL_SIZE)
        subscriber = self.session.liveliness().declare_subscriber(pattern, channel, history=True)
        return AliveWatcher(self._remember(subscriber), pattern)

    def alive_now(self, pattern: str, timeout_s: float = 2.0) -> list[str]:
        """Keys of the liveliness tokens under `pattern` alive now, sorted."""
        replies = self.session.liveliness().get(pattern, timeout=timeout_s)
        return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)

    @staticmethod
    def wait_matching(publisher: zenoh.Publisher | zenoh.Querier, timeout_s: float) -> bool:
        """Wait until some subscriber matches `publisher` (a put before that is lost); False on timeout.

        Not for `latest_publisher`s, which have no matching status and need none: their cache serves late subscribers.
        """
        deadline = time.monotonic() + timeout_s
        while not publisher.matching_status.matching:  # the status object itself is always truthy
            if time.monotonic() >= deadline:
                return False
            time.sleep(MATCHING_POLL_S)
        return True

    @property
    def closed(self) -> bool:
        """Whether `close()` has run."""
        return self._closed

    def close(self) -> None:
        """Undeclare everything (advanced subscribers first, then the rest newest first) and close the session.
        Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        for entity in [*self._advanced_subscribers, *reversed(self._entities)]:
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass  # already undeclared by its user; closing must go on
        self._advanced_subscribers.clear()
        self._entities.clear()
        self.session.close()


class Hub:
    """The one-machine hub: a peer session listening on `config.hub`, open until `close()`.

    It carries no traffic of its own; it is the fixed address through which peers find each other.
    """

    def __init__(self, config: BusConfig) -> None:
        self.config = config
        self.session = zenoh.open(zenoh_config(config, listen=True))

    def __enter__(self) -> Hub:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the session (safe to call twice)."""
        if not self.session.is_closed():
            self.session.close()


def run_hub(config: BusConfig, stop: threading.Event | Callable[[], bool], poll_s: float = 0.1) -> None:
    """Keep a `Hub` open until `stop` is set (an Event) or returns True (a callable); for the launcher's hub
    process."""
    stopped = stop.is_set if isinstance(stop, threading.Event) else stop
    with Hub(config):
        while not stopped():
            time.sleep(poll_s)
