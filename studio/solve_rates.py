"""The gallery's agent column: how often a chosen agent solves each level of a set, scored as `impulse eval` scores
(`learner.scoring`, Kinetix's protocol: every level played `attempts` times from its start, the agent's sampled
actions, the agent's environment settings).

Levels are loaded into the agent's size; one that does not fit (an M level for an S agent) is listed with the reason
instead of a rate. Results are kept per (set, agent, attempts) until a level file of the set changes, so reopening a
set costs nothing.

The levels are scored in chunks of `CHUNK_LEVELS` (the last one padded with repeats of its first level, whose
results are dropped), so that every chunk reuses one compiled evaluation per agent and number of attempts, however
many levels a set has, and so that `progress` can tell the page how far the scoring is: loading the agent,
compiling the evaluation (the first time, which on a CPU takes minutes: a whole episode of the policy and the
physics in one program), then levels scored of levels to score.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import jax

from impulse.engine.levels.level import Level, stack_levels
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
CHUNK_LEVELS = 16
"""Levels scored per evaluation call: every chunk of a set shares one compilation (a set with fewer levels is
scored in one call of its own size)."""


class SolveRates:
    """Scores agents on the `library`'s sets; `load_pilot` loads an agent (a run directory, `pretrained/...`)."""

    def __init__(self, library: Library, load_pilot: PilotLoader):
        self.library, self.load_pilot = library, load_pilot
        self._results: dict[tuple[str, str, int], tuple[tuple[float, ...], dict[str, Any]]] = {}
        self._compiled: set[tuple[Any, int, int]] = set()
        self._progress: dict[tuple[str, str, int], dict[str, Any]] = {}
        self._lock = threading.Lock()  # one scoring at a time: each may compile and fill the machine
        self._progress_lock = threading.Lock()

    def rates(self, set_id: str, checkpoint: str, attempts: int = DEFAULT_ATTEMPTS) -> dict[str, Any]:
        """`{"agent", "attempts", "rates": {level: solve rate}, "skipped": {level: reason}}` for the set's levels;
        `LevelInputError` when the agent cannot be loaded, `UnknownLevel` for an unknown set."""
        if not 1 <= attempts <= MAX_ATTEMPTS:
            raise LevelInputError(f"attempts must be 1 to {MAX_ATTEMPTS}, got {attempts}")
        files = self.library.files(set_id)
        stamp = tuple(_modified(path) for _, path in files)
        job = (set_id, checkpoint, attempts)
        self._tell(job, "waiting for another scoring to finish", 0, 0)
        try:
            with self._lock:
                cached = self._results.get(job)
                if cached is not None and cached[0] == stamp:
                    return cached[1]
                self._tell(job, f"loading the agent {checkpoint}", 0, 0)
                pilot = self.load_pilot(checkpoint)
                result = self._score(job, pilot, files, attempts)
                self._results[job] = (stamp, result)
                return result
        finally:
            with self._progress_lock:
                self._progress.pop(job, None)

    def progress(self, set_id: str, checkpoint: str, attempts: int = DEFAULT_ATTEMPTS) -> dict[str, Any] | None:
        """How far the scoring of (set, agent, attempts) is, while it runs: `{"what", "scored", "total",
        "elapsed_s"}` (`what`: the step it is at, `elapsed_s`: seconds since the request came); None when none
        runs."""
        with self._progress_lock:
            entry = self._progress.get((set_id, checkpoint, attempts))
            if entry is None:
                return None
            return {**{k: v for k, v in entry.items() if k != "since"},
                    "elapsed_s": round(time.monotonic() - entry["since"], 1)}

    def _tell(self, job: tuple[str, str, int], what: str, scored: int, total: int) -> None:
        with self._progress_lock:
            since = self._progress.get(job, {}).get("since", time.monotonic())
            self._progress[job] = {"what": what, "scored": scored, "total": total, "since": since}

    def _score(self, job: tuple[str, str, int], pilot: Pilot, files: list[tuple[str, Path]],
               attempts: int) -> dict[str, Any]:
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
        chunk = min(CHUNK_LEVELS, len(levels))
        size = size_class(pilot.spec.sizes)
        for start in range(0, len(levels), max(chunk, 1)):
            part_names, part = names[start:start + chunk], levels[start:start + chunk]
            compiled = (pilot.agent, chunk, attempts) in self._compiled
            what = ("scoring" if compiled else
                    f"compiling the evaluation of {pilot.name} for {chunk} levels x {attempts} attempts at size "
                    f"{size} (first use), then scoring")
            self._tell(job, what, start, len(levels))
            rates.update(_chunk_rates(pilot, part_names, _padded(part, chunk), attempts, start))
            self._compiled.add((pilot.agent, chunk, attempts))
        self._tell(job, "scoring", len(levels), len(levels))
        return {"agent": pilot.name, "attempts": attempts, "rates": rates, "skipped": skipped}


def _padded(levels: list[Level], count: int) -> list[Level]:
    """`levels` made up to `count` with repeats of the first (their results are dropped)."""
    return levels + [levels[0]] * (count - len(levels))


def _chunk_rates(pilot: Pilot, names: list[str], levels: list[Level], attempts: int,
                 offset: int) -> dict[str, float]:
    """The solve rates of `names`, the first levels of `levels` (the rest pad the chunk), each played `attempts`
    times; the key is folded with the chunk's offset so that chunks play different episodes."""
    padded = [*names, *(f"\0pad{i}" for i in range(len(levels) - len(names)))]
    sets = LevelSets(padded, stack_levels(levels), {})
    key = jax.random.fold_in(jax.random.PRNGKey(EVALUATION_SEED), offset)
    scored = score_policy(pilot.agent, pilot.params, pilot.env_params, sets, key, attempts)
    return {name: round(float(scored.table[name]["solve_rate"]), 4) for name in names}


def _modified(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return -1.0
