"""One process's connection to its run's Rerun recording, logged by a background thread.

Every process of a run (learner, curriculum service, actors) opens a `Monitor` with the same application id
(`APPLICATION_ID`) and the run's name as recording id, so the viewer merges them into one recording; each logs
under its own entity paths (`rollouts/actor-0/...`, `metrics/learner/...`).

Why a thread and two bounded queues: logging must never slow the work it watches. The caller hands over host
data and a function that logs it (`log`, `offer_frames`); both return at once. Rollout frames wait in a queue of a
few rollouts and metrics in a longer one; when a queue is full the new item is dropped and counted, never waited
for. Frames are also rate-limited (`wants_frames`: a token bucket of `frames_per_s`), so an actor on a GPU,
finishing rollouts many times a second, streams whole rollouts at the rate a person can watch.

Why the viewer is probed: Rerun's gRPC sink keeps every message in memory while it cannot reach its server, so
a process streaming to a viewer that is not running would grow without bound. The thread checks that the server's
port accepts connections (every `probe_every_s`), connects the sink only then, and while it is unreachable drops
what arrives (counted as `no_viewer`). A file sink (`path`) is always reachable.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import rerun as rr

log = logging.getLogger("impulse.monitor")

APPLICATION_ID = "impulse"
DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
PROBE_TIMEOUT_S = 0.5
FLUSH_TIMEOUT_S = 2.0

Job = Callable[[rr.RecordingStream], int]
"""Logs something into the recording; returns how many rollout frames it logged (0 for anything else)."""


def server_address(url: str) -> tuple[str, int]:
    """(host, port) of a Rerun gRPC url such as rerun+http://127.0.0.1:9876/proxy; ValueError if it is not one."""
    parsed = urlparse(url)
    if parsed.scheme not in ("rerun", "rerun+http", "rerun+https") or parsed.path != "/proxy":
        raise ValueError(f"not a Rerun gRPC url (rerun+http://HOST:PORT/proxy): {url!r}")
    if parsed.hostname is None or parsed.port is None:
        raise ValueError(f"the Rerun url {url!r} needs a host and a port")
    return parsed.hostname, parsed.port


def server_reachable(url: str, timeout_s: float = PROBE_TIMEOUT_S) -> bool:
    """Whether something accepts connections on the url's port (the Rerun server `impulse view` hosts)."""
    try:
        with socket.create_connection(server_address(url), timeout=timeout_s):
            return True
    except OSError:
        return False


def open_recording(run: str, *, url: str | None = None, path: str | Path | None = None,
                   blueprint: Any = None) -> rr.RecordingStream:
    """The run's recording stream (`run` is the recording id), logging to a gRPC server or to an .rrd file."""
    if (url is None) == (path is None):
        raise ValueError("open_recording needs exactly one of url (a viewer's server) and path (an .rrd file)")
    recording = rr.RecordingStream(APPLICATION_ID, recording_id=run)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        recording.save(str(path), default_blueprint=blueprint)
    else:
        recording.connect_grpc(url, default_blueprint=blueprint)
    return recording


class Monitor:
    """A process's background Rerun logger (see the module docstring). Use as a context manager, or `close()`."""

    def __init__(self, run: str, *, url: str | None = None, path: str | Path | None = None, blueprint: Any = None,
                 frames_per_s: float = 30.0, frame_queue: int = 2, record_queue: int = 256,
                 probe_every_s: float = 2.0):
        if (url is None) == (path is None):
            raise ValueError("a Monitor logs to exactly one of url (a viewer's server) and path (an .rrd file)")
        if url is not None:
            server_address(url)  # a malformed url fails here, in the caller, not later in the thread
        if frames_per_s < 0 or frame_queue < 1 or record_queue < 1:
            raise ValueError("frames_per_s must be >= 0 and the queues hold at least one item")
        self.run, self.url, self.path, self.blueprint = run, url, path, blueprint
        self.frames_per_s = frames_per_s
        self.probe_every_s = probe_every_s
        self.counts = {"frames_logged": 0, "rollouts_logged": 0, "rollouts_dropped": 0, "rollouts_skipped": 0,
                       "records_logged": 0, "records_dropped": 0, "no_viewer": 0, "errors": 0}
        self._frames: queue.Queue[Job] = queue.Queue(frame_queue)
        self._records: queue.Queue[Job] = queue.Queue(record_queue)
        self._tokens = 0.0
        self._tokens_at = time.monotonic()
        self._recording: rr.RecordingStream | None = None
        self.viewer_up = path is not None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, name="rerun-monitor", daemon=True)
        self._thread.start()

    # -- the caller's side (never blocks) -------------------------------------------------------------------------

    def wants_frames(self, count: int) -> bool:
        """Whether a rollout of `count` frames should be offered now: a viewer is there and the rate allows it.
        A refusal for the rate is counted as skipped (those frames are simply not streamed)."""
        if not self.viewer_up:
            return False
        now = time.monotonic()
        self._tokens = min(self._tokens + (now - self._tokens_at) * self.frames_per_s,
                           max(float(count), self.frames_per_s))
        self._tokens_at = now
        if self._tokens < count:
            self.counts["rollouts_skipped"] += 1
            return False
        self._tokens -= count
        return True

    def offer_frames(self, job: Job) -> bool:
        """Queue a rollout's frames for logging; False (and counted as dropped) when the queue is full."""
        return self._put(self._frames, job, "rollouts_dropped")

    def log(self, job: Job) -> bool:
        """Queue anything else (metrics, statistics, a gallery) for logging; False (counted) when full."""
        return self._put(self._records, job, "records_dropped")

    def _put(self, into: queue.Queue[Job], job: Job, dropped: str) -> bool:
        if self._stop.is_set():
            return False
        try:
            into.put_nowait(job)
            return True
        except queue.Full:
            self.counts[dropped] += 1
            return False

    def status(self) -> dict[str, Any]:
        """Counters for a status line (plain ints) and whether the viewer is reachable."""
        return {"viewer": self.viewer_up, **self.counts}

    def close(self, timeout_s: float = 10.0) -> None:
        """Log what is queued (if a viewer is there), flush and disconnect; waits at most `timeout_s`."""
        self._stop.set()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("the Rerun logger did not finish within %.0f s; queued data may be lost", timeout_s)

    def __enter__(self) -> Monitor:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- the logging thread --------------------------------------------------------------------------------------

    def _probe(self) -> None:
        up = self.url is None or server_reachable(self.url)
        if up and self._recording is None:
            self._recording = open_recording(self.run, url=self.url, path=self.path, blueprint=self.blueprint)
            log.info("streaming to Rerun at %s (recording %s)", self.url or self.path, self.run)
        elif up and not self.viewer_up and self.url is not None:
            # The viewer came back: Rerun's sink does not reconnect to a restarted server by itself.
            assert self._recording is not None
            self._recording.connect_grpc(self.url, default_blueprint=self.blueprint)
        if up != self.viewer_up and self.url is not None:
            log.info("Rerun viewer at %s %s", self.url, "reachable" if up else "gone: dropping what is logged")
        self.viewer_up = up

    def _run(self, job: Job, frames: bool) -> None:
        if not self.viewer_up or self._recording is None:
            self.counts["no_viewer"] += 1
            return
        try:
            logged = job(self._recording)
        except Exception:  # a bad record must not end the monitoring of a long run
            self.counts["errors"] += 1
            log.exception("could not log to Rerun")
            return
        if frames:
            self.counts["frames_logged"] += logged
            self.counts["rollouts_logged"] += 1
        else:
            self.counts["records_logged"] += 1

    def _next(self) -> tuple[Job, bool] | None:
        for source, frames in ((self._records, False), (self._frames, True)):
            try:
                return source.get_nowait(), frames
            except queue.Empty:
                continue
        return None

    def _work(self) -> None:
        probed_at = -float("inf")
        while True:
            if time.monotonic() - probed_at >= self.probe_every_s:
                self._probe()
                probed_at = time.monotonic()
            item = self._next()
            if item is None:
                if self._stop.is_set():
                    break
                time.sleep(0.02)
                continue
            self._run(*item)
        if self._recording is not None:
            try:
                self._recording.flush(timeout_sec=FLUSH_TIMEOUT_S)
                self._recording.disconnect()
            except RuntimeError as err:  # the viewer went away with data in flight
                log.warning("could not flush the Rerun recording: %s", err)
