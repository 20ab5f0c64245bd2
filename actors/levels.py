"""Where an actor's levels come from. An actor asks its level source for the batch of levels its environments
take their next episodes from, once per rollout; the local source below reads the run's `env.levels` (a level
file or folder, our hand-made set, or fresh random levels each rollout). A curriculum client implements the same
interface, so the actor does not change when levels come from a curriculum service."""

from __future__ import annotations

from typing import Protocol

import jax

from engine.env.config import EnvConfig
from engine.levels.level import Level
from engine.levels.sets import RANDOM, load_level_set
from engine.physics.sizes import SceneSizes

Array = jax.Array


class LevelSource(Protocol):
    description: str
    """A few words for the status display, e.g. "handmade:s_easy_car_right (1 level)"."""

    def next_batch(self, key: Array) -> Level:
        """The level batch (leading axis K, K fixed for the source) for the next rollout."""


class LocalLevels:
    """The run's own level set, or `num_levels` fresh random levels per batch."""

    def __init__(self, env: EnvConfig, sizes: SceneSizes, num_levels: int):
        self.random = env.levels == RANDOM
        if self.random:
            from engine.levels.generator import sample_random_levels  # only random runs pay for its import

            self._sample = lambda key: sample_random_levels(key, num_levels, sizes)
            self.description = f"random ({num_levels} per rollout)"
            self.names: list[str] = []
            self._levels: Level | None = None
        else:
            self.names, self._levels = load_level_set(env.levels, sizes)
            count = len(self.names)
            self.description = f"{env.levels} ({count} level{'s' if count != 1 else ''})"

    def next_batch(self, key: Array) -> Level:
        if self._levels is not None:
            return self._levels
        return self._sample(key)
