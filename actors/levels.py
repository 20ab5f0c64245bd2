"""Where an actor's levels come from. An actor asks its level source for the batch of levels its environments
take their next episodes from, once per rollout. The local source reads the run's `env.levels` (a level file or
folder, or our hand-made set); the curriculum source asks the curriculum service, the authority on levels in a
run on random levels. Both hand out a `curriculum.state.LevelBatch` (levels, whether each is trained on, where
each came from), so the actor does not care which one it has.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Protocol

import jax
import jax.numpy as jnp

from impulse.bus.codec import Rejected
from impulse.bus.levels import LEVEL_QUERY_TIMEOUT_S, WAIT_PARAMETER, decode_level_batch
from impulse.bus.session import Bus
from impulse.curriculum.state import ORIGIN_NEW, LevelBatch
from impulse.curriculum.wire import level_batch_from_message, level_batch_schema
from impulse.engine.env.config import EnvConfig
from impulse.engine.levels.level import Level
from impulse.engine.levels.sets import RANDOM, load_level_set
from impulse.engine.physics.sizes import SceneSizes

Array = jax.Array
log = logging.getLogger(__name__)

WAIT_LOG_EVERY_S = 10.0


class LevelSource(Protocol):
    description: str
    """A few words for the status display, e.g. "handmade:s_easy_car_right (1 level)"."""

    reports_results: bool
    """Whether the source wants per-level results back (a curriculum does; a fixed level set does not)."""

    waiting: bool
    """Whether the last `next_batch` is still waiting for levels (shown on the status line)."""

    template: LevelBatch
    """The shapes and dtypes of every batch `next_batch` hands out (`jax.ShapeDtypeStruct` leaves), known before
    the first: the actor compiles its rollout for them while it waits for levels."""

    def next_batch(self, key: Array, while_waiting: Callable[[], bool] | None = None) -> LevelBatch | None:
        """The level batch (leading axis K, K fixed for the source) for the next rollout. `while_waiting` is
        called now and then if the levels are slow to come (the actor keeps its status line fresh with it); when
        it returns False the source stops waiting and returns None (the actor was asked to stop)."""


def fixed_batch(levels: Level) -> LevelBatch:
    """A batch of levels that are all trained on."""
    count = levels.roles.shape[0]
    return LevelBatch(levels, jnp.ones(count, bool), jnp.full(count, ORIGIN_NEW, jnp.int32))


class LocalLevels:
    """The run's own level set (a file, a folder or the hand-made set)."""

    reports_results = False
    waiting = False

    def __init__(self, env: EnvConfig, sizes: SceneSizes):
        if env.levels == RANDOM:
            raise ValueError("random levels come from the curriculum service (CurriculumLevels), not a local set")
        self.names, levels = load_level_set(env.levels, sizes)
        self._batch = fixed_batch(levels)
        self.template = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), self._batch)
        count = len(self.names)
        self.description = f"{env.levels} ({count} level{'s' if count != 1 else ''})"

    def next_batch(self, key: Array, while_waiting: Callable[[], bool] | None = None) -> LevelBatch:
        return self._batch


class CurriculumLevels:
    """Level batches pulled from the curriculum service's `levels/sample` queryable, one query per rollout.

    A batch that does not fit the schema the actor's rollout was compiled for is refused (counted by reason) and
    asked for again; while no service answers, the actor waits, logging every `WAIT_LOG_EVERY_S` seconds."""

    reports_results = True

    def __init__(self, bus: Bus, template: LevelBatch, method: str, timeout_s: float = LEVEL_QUERY_TIMEOUT_S):
        self.bus = bus
        self.template = template
        self.schema = level_batch_schema(template)
        self.size = int(template.train.shape[0])
        self.timeout_s = timeout_s
        self.description = f"curriculum {method} ({self.size} per rollout)"
        self.waiting = False

    def next_batch(self, key: Array, while_waiting: Callable[[], bool] | None = None) -> LevelBatch | None:
        del key  # the service draws the levels
        key_expr = self.bus.keys.levels_sample
        started = last_log = time.monotonic()
        while True:
            for payload in self.bus.get(key_expr, parameters=f"n={self.size};{WAIT_PARAMETER}={self.timeout_s:g}",
                                        timeout_s=self.timeout_s):
                try:
                    message = decode_level_batch(payload, self.bus.keys.run)
                    batch = level_batch_from_message(message, self.schema, self.template)
                except Rejected as err:
                    self.bus.rejects.record(err.reason, key_expr, err.detail)
                    continue
                self.waiting = False
                return jax.tree.map(jnp.asarray, batch)
            self.waiting = True
            if while_waiting is not None and not while_waiting():
                return None
            time.sleep(0.2)  # nobody answered (no service yet): a get with no queryable returns at once
            if time.monotonic() - last_log >= WAIT_LOG_EVERY_S:
                last_log = time.monotonic()
                log.warning("no level batch from the curriculum service on %s for %.0f s; waiting", key_expr,
                            last_log - started)
