"""New levels made ahead of the requests that need them: the no-op filter off the curriculum service's request path.

A new batch of random levels passes Kinetix's no-op filter (`curriculum.noop_filter`), which simulates every
candidate under the all-zero action: far costlier than anything else a level request does. A `LevelMaker` runs the
filter on a thread of its own and keeps up to `depth` filtered batches ready, so the request path only takes one.

When requests outrun the thread and none is ready, `take` draws the batch unfiltered at once (a few random
levels, cheap) and counts it, rather than keep an actor waiting past its timeout: the filter is soft in Kinetix
too, and a level that doing nothing solves scores as unlearnable in every curriculum that keeps a buffer. A batch
the request did not use (a replayed batch needs no new levels) is handed back with `give_back`: a filtered one is
served next, an unfiltered one dropped (and not counted).

Nothing here is checkpointed: the ready batches are random levels no one has seen, remade after a restart.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable

import jax

from impulse.engine.levels.level import Level

log = logging.getLogger(__name__)

Array = jax.Array
MakeLevels = Callable[[Array], Level]
"""A jitted function from a key to one batch of new levels."""


class LevelMaker:
    """Keeps up to `depth` batches of `filtered(key)` ready, made on its own thread (see the module docstring);
    `unfiltered(key)` makes a batch at once when none is. The keys are `key` folded with the batch's number."""

    def __init__(self, filtered: MakeLevels, unfiltered: MakeLevels, key: Array, depth: int):
        if depth < 1:
            raise ValueError(f"a level maker keeps at least one batch ready, not {depth}")
        self._filtered = filtered
        self._unfiltered = unfiltered
        self._key = key
        self.depth = depth
        self._ready: collections.deque[Level] = collections.deque()
        self._changed = threading.Condition()
        self._stopping = False
        self._unfiltered_compiled = False
        self._failure: BaseException | None = None
        self._numbered = 0  # batches drawn so far, filtered or not: the next one's key (0 is the compile's)
        self.made = 0
        """Filtered batches made."""
        self.unfiltered = 0
        """Batches drawn unfiltered because none was ready, and used."""
        self.filter_seconds = 0.0
        """Time the thread spent making filtered batches."""
        self._thread = threading.Thread(target=self._run, daemon=True, name="levels-ahead")

    def start(self, timeout_s: float = 600.0) -> None:
        """Start the thread and wait for its first batch (which includes compiling the filter)."""
        self._thread.start()
        with self._changed:
            if not self._changed.wait_for(lambda: self._ready or self._failure is not None, timeout_s):
                raise TimeoutError(f"no filtered level batch within {timeout_s:.0f} s")
        self._raise_failure()

    def close(self) -> None:
        """Stop the thread (after the batch it is making)."""
        with self._changed:
            self._stopping = True
            self._changed.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=60)

    @property
    def ready(self) -> int:
        """Batches ready now."""
        return len(self._ready)

    @property
    def can_draw_unfiltered(self) -> bool:
        """Whether `take` draws unfiltered when no batch is ready (once that draw is compiled) or waits."""
        return self._unfiltered_compiled

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def take(self) -> tuple[Level, bool]:
        """(a batch of new levels, whether it passed the filter): a ready one, else one drawn unfiltered now; until
        the unfiltered draw is compiled (right after the first filtered batch), waits for a ready one instead."""
        with self._changed:
            self._raise_failure()
            if not self._ready and not self._unfiltered_compiled:
                self._changed.wait_for(lambda: self._ready or self._failure is not None)
                self._raise_failure()
            if self._ready:
                batch = self._ready.popleft()
                self._changed.notify_all()
                return batch, True
            key = self._next_key()
        self.unfiltered += 1
        if self.unfiltered == 1:
            log.warning("level requests outran the no-op filter's thread: new levels are drawn unfiltered until it "
                        "catches up (counted as `unfiltered` in the curriculum's status)")
        return self._unfiltered(key), False

    def give_back(self, batch: Level, filtered: bool) -> None:
        """A taken batch that went unused (as `take` returned it): a filtered one is served next; an unfiltered one
        is dropped, and not counted as served."""
        with self._changed:
            if filtered:
                self._ready.appendleft(batch)
            else:
                self.unfiltered -= 1

    def _next_key(self) -> Array:
        self._numbered += 1
        return jax.random.fold_in(self._key, self._numbered)

    def _raise_failure(self) -> None:
        if self._failure is not None:
            raise RuntimeError("making filtered levels failed") from self._failure

    def _run(self) -> None:
        try:
            while True:
                with self._changed:
                    self._changed.wait_for(lambda: self._stopping or len(self._ready) < self.depth)
                    if self._stopping:
                        return
                    key = self._next_key()
                started = time.perf_counter()
                batch = jax.block_until_ready(self._filtered(key))
                self.filter_seconds += time.perf_counter() - started
                with self._changed:
                    self._ready.append(batch)
                    self.made += 1
                    self._changed.notify_all()
                if not self._unfiltered_compiled:
                    jax.block_until_ready(self._unfiltered(jax.random.fold_in(self._key, 0)))
                    with self._changed:
                        self._unfiltered_compiled = True
        except BaseException as err:  # noqa: BLE001 - handed to the request path, which raises it
            with self._changed:
                self._failure = err
                self._changed.notify_all()
