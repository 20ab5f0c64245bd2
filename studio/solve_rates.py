"""The gallery's agent column: how often a chosen agent solves each level of a set, scored as `impulse eval` scores
(`learner.scoring`, Kinetix's protocol: every level played `attempts` times from its start, the agent's sampled
actions, the agent's environment settings).

Levels are loaded into the agent's size; one that does not fit (an M level for an S agent) is listed with the reason
instead of a rate. Results are kept per (set, agent, attempts) until a level file of the set changes, so reopening a
set costs nothing; the first scoring of a set compiles the evaluation for its number of levels.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import jax
from impulse.engine.levels.level import stack_levels
from impulse.engine.levels.summary import size_class
from impulse.learner.scoring import LevelSets, score_policy
from impulse.studio.level_io import LevelInputError, load_file
from impulse.studio.library import Library
from impulse.studio.play import Pilot
from impulse.studio.protocol import PilotLoader

DEFAULT_ATTEMPTS = 10
MAX_ATTEMPTS = 100
EVALUATION_SEED = 0
"""One key for every scoring, so the same agent on the same set gives the same rates."""


class SolveRates:
    """Scores agents on the `library`'s sets; `load_pilot` loads an agent (a run directory, `pretrained/...`)."""

    def __init__(self, library: Library, load_pilot: PilotLoader):
        self.library, self.load_pilot = library, load_pilot
        self._pilots: dict[str, Pilot] = {}
        self._results: dict[tuple[str, str, int], tuple[tuple[float, ...], dict[str, Any]]] = {}
        self._lock = threading.Lock()  # one scoring at a time: each may compile and fill the machine

    def rates(self, set_id: str, checkpoint: str, attempts: int = DEFAULT_ATTEMPTS) -> dict[str, Any]:
        """`{"agent", "attempts", "rates": {level: solve rate}, "skipped": {level: reason}}` for the set's levels;
        `LevelInputError` when the agent cannot be loaded, `UnknownLevel` for an unknown set."""
        if not 1 <= attempts <= MAX_ATTEMPTS:
            raise LevelInputError(f"attempts must be 1 to {MAX_ATTEMPTS}, got {attempts}")
        files = self.library.files(set_id)
        stamp = tuple(_modified(path) for _, path in files)
        with self._lock:
            cached = self._results.get((set_id, checkpoint, attempts))
            if cached is not None and cached[0] == stamp:
                return cached[1]
            pilot = self._pilot(checkpoint)
            result = self._score(pilot, files, attempts)
            self._results[(set_id, checkpoint, attempts)] = (stamp, result)
            return result

    def _pilot(self, checkpoint: str) -> Pilot:
        if checkpoint not in self._pilots:
            self._pilots[checkpoint] = self.load_pilot(checkpoint)
        return self._pilots[checkpoint]

    @staticmethod
    def _score(pilot: Pilot, files: list[tuple[str, Path]], attempts: int) -> dict[str, Any]:
        names, levels, skipped = [], [], {}
        for name, path in files:
            try:
                levels.append(load_file(path, pilot.spec.sizes).level)
                names.append(name)
            except LevelInputError as err:
                problems = err.problems or [err.message]
                too_large = any(problem.startswith("too large for the size") for problem in problems)
                skipped[name] = (f"too large for the agent's size {size_class(pilot.spec.sizes)}" if too_large
                                 else "; ".join(problems))
        rates: dict[str, float] = {}
        if levels:
            sets = LevelSets(names, stack_levels(levels), {})
            scored = score_policy(pilot.agent, pilot.params, pilot.env_params, sets,
                                  jax.random.PRNGKey(EVALUATION_SEED), attempts)
            rates = {name: round(float(row["solve_rate"]), 4) for name, row in scored.table.items()}
        return {"agent": pilot.name, "attempts": attempts, "rates": rates, "skipped": skipped}


def _modified(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return -1.0
