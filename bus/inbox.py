"""Receiving handles: bounded queues drained in the caller's own thread.

Zenoh can hand each sample to a Python callback, but a slow callback is an unbounded queue (the reference measured
a 124 MB backlog) and work done inside it runs on zenoh's threads. Here nothing is done in a callback but queueing:
every subscription and every queryable feeds a bounded `Mailbox` (a callback that only appends the sample or query,
and counts what it has to drop when full, so no drop goes uncounted), liveliness watchers feed a zenoh ring channel,
and the owner drains them with `poll` or `wait` wherever it decodes anyway. Nothing blocks zenoh's receive thread:
a full zenoh FIFO channel would, stalling everything the session receives until its owner drains it (anyone on
the bus can send a flood of queries to a service that is busy). Back-pressure is the protocol's business
(credits), never a full queue's: zenoh's blocking gives up silently after a while.
Zenoh channels have no receive-with-timeout, so `wait` polls with a short sleep (at most WAIT_SLEEP_MAX_S).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import zenoh

WAIT_SLEEP_MIN_S = 0.0005
WAIT_SLEEP_MAX_S = 0.005
"""Bounds of the sleep between two polls in `wait`: the latency it adds is at most this."""

_T = TypeVar("_T")


def _drain(try_recv: Callable[[], Any], convert: Callable[[Any], _T | None], max_items: int | None) -> list[_T]:
    items: list[_T] = []
    while max_items is None or len(items) < max_items:
        raw = try_recv()
        if raw is None:
            break
        item = convert(raw)
        if item is not None:
            items.append(item)
    return items


def _wait(poll_one: Callable[[], _T | None], timeout_s: float) -> _T | None:
    deadline = time.monotonic() + timeout_s
    sleep = WAIT_SLEEP_MIN_S
    while True:
        item = poll_one()
        if item is not None:
            return item
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        time.sleep(min(sleep, left))
        sleep = min(sleep * 2, WAIT_SLEEP_MAX_S)


@dataclass(frozen=True)
class Received:
    """One sample: its key, its payload (one copy out of zenoh) and its attachment, if any."""

    key: str
    payload: bytes
    attachment: bytes | None


def _received(sample: zenoh.Sample) -> Received | None:
    if sample.kind != zenoh.SampleKind.PUT:
        return None  # nothing in the protocol deletes keys; a DELETE carries no message
    attachment = sample.attachment
    return Received(
        key=str(sample.key_expr),
        payload=sample.payload.to_bytes(),
        attachment=attachment.to_bytes() if attachment is not None else None,
    )


class Mailbox:
    """A bounded queue of samples (or queries) that zenoh's callback fills and the owner's thread empties.

    When full it drops the newest item (`drop_oldest=False`: what is queued is kept in order) or the oldest
    (`drop_oldest=True`: only the newest matter), and counts each drop in `dropped`. The callback does nothing else:
    no decoding, no copy, no device work on zenoh's threads. A dropped query is finalised unanswered when it is
    released, so its asker's `get` ends with no reply.
    """

    def __init__(self, capacity: int, drop_oldest: bool) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"a mailbox needs a capacity >= 1, got {capacity!r}")
        self.capacity = capacity
        self.drop_oldest = drop_oldest
        self.dropped = 0
        self._samples: deque[tuple[float, zenoh.Sample]] = deque()  # (time.monotonic() on arrival, sample)
        self._lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._lock:
            if len(self._samples) >= self.capacity:
                self.dropped += 1
                if not self.drop_oldest:
                    return
                self._samples.popleft()
            self._samples.append((time.monotonic(), sample))

    def try_recv(self) -> zenoh.Sample | None:
        """The oldest queued sample, or None."""
        arrived = self.try_recv_arrived()
        return None if arrived is None else arrived[1]

    def try_recv_arrived(self) -> tuple[float, zenoh.Sample] | None:
        """The oldest queued sample with the `time.monotonic()` of its arrival, or None."""
        with self._lock:
            return self._samples.popleft() if self._samples else None


class Inbox:
    """Samples of one subscription, waiting in a `Mailbox` until the owner takes them."""

    def __init__(self, subscriber: Any, key: str, mailbox: Mailbox) -> None:
        self.subscriber = subscriber
        self.key = key
        self.mailbox = mailbox

    @property
    def dropped(self) -> int:
        """Samples dropped so far because the mailbox was full (see `Mailbox`)."""
        return self.mailbox.dropped

    def poll(self, max_items: int | None = None) -> list[Received]:
        """Every sample waiting now (at most `max_items`), without blocking."""
        return _drain(self.mailbox.try_recv, _received, max_items)

    def wait(self, timeout_s: float) -> Received | None:
        """The next sample, waiting up to `timeout_s` seconds for it; None if none came."""
        return _wait(lambda: next(iter(self.poll(1)), None), timeout_s)


class IncomingQuery:
    """A query received by a queryable, answered from the owner's thread with exactly one `reply`.

    Answering (or `reply_error`) also finalises the query, so the asker's `get` returns at once instead of
    waiting for its timeout.
    """

    def __init__(self, query: zenoh.Query, reply_key: str, arrived: float | None = None) -> None:
        """`arrived`: the `time.monotonic()` at which zenoh handed the query over (None: now)."""
        self._query = query
        self.arrived = time.monotonic() if arrived is None else arrived
        self._reply_key = reply_key
        self.key = str(query.key_expr)
        self.parameters: dict[str, str] = dict(query.parameters)
        payload = query.payload
        self.payload: bytes | None = payload.to_bytes() if payload is not None else None
        self.answered = False

    @property
    def waited_s(self) -> float:
        """Seconds since the query arrived: one that waited longer than its asker waits is answered in vain."""
        return time.monotonic() - self.arrived

    def reply(self, payload: bytes | bytearray, *, attachment: bytes | None = None) -> None:
        """Send `payload` to the asker and finish the query."""
        self._finish(lambda: self._query.reply(self._reply_key, payload, attachment=attachment))

    def reply_error(self, message: str) -> None:
        """Tell the asker why there is no answer (its `get` drops errors) and finish the query."""
        self._finish(lambda: self._query.reply_err(message.encode("utf-8")))

    def _finish(self, send: Callable[[], None]) -> None:
        if self.answered:
            raise RuntimeError(f"query on {self.key!r} was already answered")
        self.answered = True
        try:
            send()
        finally:
            self._query.drop()


class QueryInbox:
    """Queries to one queryable, waiting in a `Mailbox` until the owner answers them. A full mailbox drops the
    newest query and counts it (`dropped`): its asker gets no reply, and nothing else the session receives waits."""

    def __init__(self, queryable: zenoh.Queryable, key: str, mailbox: Mailbox) -> None:
        self.queryable = queryable
        self.key = key
        self.mailbox = mailbox
        self._concrete = not any(ch in key for ch in "*$")

    @property
    def dropped(self) -> int:
        """Queries dropped so far because the mailbox was full."""
        return self.mailbox.dropped

    def _incoming(self, arrived_query: tuple[float, zenoh.Query]) -> IncomingQuery:
        arrived, query = arrived_query
        # Replies must name a concrete key: the queryable's own, or (serving a pattern) the one asked for.
        return IncomingQuery(query, self.key if self._concrete else str(query.key_expr), arrived)

    def poll(self, max_items: int | None = None) -> list[IncomingQuery]:
        """Every query waiting now (at most `max_items`), without blocking."""
        return _drain(self.mailbox.try_recv_arrived, self._incoming, max_items)

    def wait(self, timeout_s: float) -> IncomingQuery | None:
        """The next query, waiting up to `timeout_s` seconds for it; None if none came."""
        return _wait(lambda: next(iter(self.poll(1)), None), timeout_s)


def _alive_event(sample: zenoh.Sample) -> tuple[str, bool]:
    return str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT


class AliveWatcher:
    """Liveliness changes under a pattern: (key, True) when a token appears, (key, False) when it goes.

    Tokens alive when the watcher is declared are reported first (history). The channel is a ring: a watcher
    nobody polls must not stall zenoh's receive thread, so the oldest events are dropped once it is full.
    """

    def __init__(self, subscriber: zenoh.Subscriber, pattern: str) -> None:
        self.subscriber = subscriber
        self.pattern = pattern

    def poll(self, max_items: int | None = None) -> list[tuple[str, bool]]:
        """Every change waiting now, oldest first, without blocking."""
        return _drain(self.subscriber.try_recv, _alive_event, max_items)

    def wait(self, timeout_s: float) -> tuple[str, bool] | None:
        """The next change, waiting up to `timeout_s` seconds for it; None if none came."""
        return _wait(lambda: next(iter(self.poll(1)), None), timeout_s)
