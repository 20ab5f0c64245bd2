"""The studio's line to a running run's curriculum service: the Curriculum page's buffer table and thumbnails, its
knobs, and the editor's "Send to run", all asked over the run's bus as the operator role (the only role a router
lets ask them) through `curriculum.client`.

`impulse studio --run RUN_DIR` builds the link from the run's configuration (`deploy.commands.studio`), since the
studio cannot read run configurations itself; `studio.app` serves it under `/api/curriculum` and `/api/inject`.
Each request opens a short session and closes it, so a run that stops or restarts between two requests is found
again; a dead run is a clear error in the page, never a stuck server.

What the service's report does not carry, the link keeps itself: a history of the buffer's counters (inserted,
evicted, rejected, replay batches, ...), one sample per report it fetched, for the page's "over time" chart (so it
covers the time the studio was asking: the page asks every 5 s while it is shown), and the levels this studio sent
in, with when, so the page can say which buffered levels were injected. (The buffer itself keeps no origin: an
injected level enters with no parent and generation 0, as a new one does; a level sent in by `impulse curriculum
inject` therefore shows as "new".) Thumbnails are drawn when the page asks for one, not for every report.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections import OrderedDict, deque
from pathlib import Path
from typing import Any

import jax
import numpy as np

from impulse.bus.config import BusConfig
from impulse.curriculum.client import CurriculumClient
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.generator import sample_random_level
from impulse.engine.levels.kinetix_json import level_to_json_dict
from impulse.engine.levels.level import Level
from impulse.engine.pytree import tree_from_arrays
from impulse.monitor.png import render_level
from impulse.studio.library import THUMBNAIL_SCALE, UnknownLevel, png_bytes

ANSWER_TIMEOUT_S = 15.0
THUMBNAILS_KEPT = 256
"""Buffer levels kept in memory for their thumbnails (by level id), newest first; a level that left the buffer ages
out."""
MAX_POINTS = 4096
"""The most buffer levels whose score and solve rate a report carries for the page's scatter plot."""
HISTORY_KEPT = 4000
"""Counter samples kept for the "over time" chart (at one per 5 s: five and a half hours)."""
HISTORY_FIELDS = ("count_inserted", "count_evicted", "count_rejected", "count_replay_batches", "count_new_batches",
                  "count_mutate_batches", "buffer_fill", "score_mean")
"""The buffer summary's fields kept per sample (`curriculum.stats.buffer_summary`)."""


class CurriculumRefused(ValueError):
    """The run's curriculum service answered, and refused the request (or sent a reply the studio cannot use); the
    message gives its reason."""


def json_ready(value: Any) -> Any:
    """`value` with every NaN or infinity replaced by None: a level that has no episodes yet has no solve rate,
    and strict JSON (a browser's) has no NaN."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: json_ready(item) for key, item in value.items()}
    if isinstance(value, list):
        return [json_ready(item) for item in value]
    return value


class CurriculumLink:
    """Run `run`'s curriculum service on `bus`, for a studio; `spec` and `env_params` are the run's environment
    (its scene sizes, to read the buffered levels the service sends, and its physics settings, written into the
    level files of `snapshot`)."""

    def __init__(self, bus: BusConfig, run: str, spec: EnvSpec, env_params: EnvParams | None = None,
                 timeout_s: float = ANSWER_TIMEOUT_S):
        self.bus, self.run, self.timeout_s = bus, run, timeout_s
        self.spec, self.env_params = spec, env_params or EnvParams()
        self.sizes = spec.sizes
        self._levels: OrderedDict[str, Level] = OrderedDict()
        self._thumbnails: dict[str, bytes] = {}
        self._history: deque[dict[str, Any]] = deque(maxlen=HISTORY_KEPT)
        self._injected: OrderedDict[str, float] = OrderedDict()
        self._template: Level | None = None
        self._lock = threading.Lock()

    def _client(self) -> CurriculumClient:
        return CurriculumClient(self.bus, self.run, f"studio-{os.getpid()}", self.timeout_s)

    def inject(self, document: dict[str, Any]) -> dict[str, Any]:
        """Send a Kinetix level-file object into the buffer: `{"ok": true, "slot", "level_id", "evicted"}`, or
        `{"ok": false, "error"}` with the service's reason; `CurriculumUnreachable` when it could not be asked."""
        with self._client() as client:
            reply = client.inject(document)
        if reply.get("ok") and isinstance(reply.get("level_id"), str):
            with self._lock:
                self._injected[reply["level_id"]] = time.time()
                while len(self._injected) > HISTORY_KEPT:
                    self._injected.popitem(last=False)
        return reply

    def knobs(self, assignments: list[str] | None = None) -> dict[str, Any]:
        """The live knobs (`{"ok", "method", "knobs"}`), after `assignments` ("replay_prob=0.8", ...) when given,
        checked by the service as for `impulse curriculum set`; `{"ok": false, "error"}` when refused,
        `CurriculumUnreachable` when it could not be asked."""
        with self._client() as client:
            return client.knobs(assignments)

    def buffer(self, top: int, points: bool = False) -> dict[str, Any]:
        """The buffer's report (`curriculum.stats.inspect_report`: summary, histograms, live knobs) with its
        `top` levels by score as rows whose `level_id` and `parent_id` are hexadecimal strings (a browser's
        numbers cannot hold 64 bits) and whose `origin` says how the level came ("injected" for a level this
        studio sent in); their thumbnails are served by `thumbnail`. Also `history` (the counter samples so far,
        this one included), `injections` (`{level_id, t}` of the levels this studio sent in) and, with `points`,
        `points`: the score, solve rate and episodes of every buffered level (at most MAX_POINTS), columns by name.
        Raises `CurriculumUnreachable`, or `CurriculumRefused` with the service's reason."""
        report, levels, rows = self._best(top, MAX_POINTS if points else 0)
        with self._lock:
            injected = dict(self._injected)
        for row, level in zip(report.get("top", []), levels, strict=True):
            self._hex_ids(row, injected)
            with self._lock:
                self._levels[row["level_id"]] = level
                self._levels.move_to_end(row["level_id"])
        with self._lock:
            while len(self._levels) > THUMBNAILS_KEPT:
                gone, _ = self._levels.popitem(last=False)
                self._thumbnails.pop(gone, None)
            history = list(self._history)
        extra: dict[str, Any] = {"history": history,
                                 "injections": [{"level_id": k, "t": t} for k, t in injected.items()]}
        if points:
            for row in rows:
                self._hex_ids(row, injected)
            extra["points"] = {name: [row.get(name) for row in rows]
                               for name in ("level_id", "score", "solve_rate", "episodes", "origin")}
        return json_ready({"run": self.run, **report, **extra})

    @staticmethod
    def _hex_ids(row: dict[str, Any], injected: dict[str, float]) -> None:
        """Give an inspect row hexadecimal ids and its origin: injected (by this studio), mutated, or new."""
        row["level_id"] = f"{int(row['level_id']):016x}"
        row["parent_id"] = f"{int(row['parent_id']):016x}"
        if row["level_id"] in injected:
            row["origin"] = "injected"
        elif row.get("generation", 0) > 0:
            row["origin"] = f"mutated, generation {row['generation']}"
        else:
            row["origin"] = "new"

    def thumbnail(self, level_id: str) -> bytes:
        """The PNG of a level the last `buffer` calls listed (drawn at the first request); `UnknownLevel` for any
        other."""
        with self._lock:
            png, level = self._thumbnails.get(level_id), self._levels.get(level_id)
        if png is not None:
            return png
        if level is None:
            raise UnknownLevel(f"no thumbnail of buffer level {level_id!r}: refresh the curriculum page")
        png = png_bytes(render_level(level, scale=THUMBNAIL_SCALE))
        with self._lock:
            if level_id in self._levels:
                self._thumbnails[level_id] = png
        return png

    def snapshot(self, folder: Path, top: int) -> int:
        """Write the buffer's `top` levels by score into `folder` as Kinetix level files named
        `<rank>_<level id>` (the studio's gallery set of the run), in place of the files a previous snapshot
        wrote; how many. Raises `CurriculumUnreachable`, or `CurriculumRefused` with the service's reason."""
        report, levels, _ = self._best(top)
        rows = report.get("top", [])
        for old in folder.glob("*.json"):
            old.unlink()
        for rank, (row, level) in enumerate(zip(rows, levels, strict=True), start=1):
            document = level_to_json_dict(level, self.sizes, self.env_params.sim, self.spec.frame_skip,
                                          self.spec.solver)
            (folder / f"{rank:03d}_{int(row['level_id']):016x}.json").write_text(json.dumps(document))
        return len(levels)

    def _best(self, top: int, points: int = 0) -> tuple[dict[str, Any], list[Level], list[dict[str, Any]]]:
        """The service's inspect report of its `top` levels by score, those levels (in the report's order), and,
        with `points` > 0, the rows of up to that many buffered levels (without their scenes; asked in the same
        session). Records a history sample of the report's counters."""
        with self._client() as client:
            reply = client.inspect(top, levels=True)
            if reply.error is not None:
                raise CurriculumRefused(f"the curriculum service refused: {reply.error}")
            rows = reply.report.get("top", [])
            wanted = min(int(reply.report.get("summary", {}).get("buffer_size", 0)), points)
            if wanted > len(rows) >= top:  # fewer rows than asked for: they are every level buffered already
                more = client.inspect(wanted, levels=False)
                if more.error is not None:
                    raise CurriculumRefused(f"the curriculum service refused: {more.error}")
                rows = more.report.get("top", [])
        rows = [dict(row) for row in rows[:points]] if points else []
        summary = reply.report.get("summary", {})
        with self._lock:
            self._history.append({"t": round(time.time(), 3), "policy_version": reply.report.get("policy_version"),
                                  **{name: summary.get(name) for name in HISTORY_FIELDS}})
        count = len(reply.report.get("top", []))
        if count == 0:
            return reply.report, [], rows
        if not reply.arrays:
            raise CurriculumRefused("the curriculum service sent its report without the levels")
        if self._template is None:  # traced once: tracing the generator takes a while on a busy machine
            self._template = jax.eval_shape(lambda key: sample_random_level(key, self.sizes), jax.random.PRNGKey(0))
        template = self._template
        arrays = {name: np.asarray(values) for name, values in reply.arrays.items()}
        levels = [tree_from_arrays({name: values[i] for name, values in arrays.items()}, template)
                  for i in range(count)]
        return reply.report, levels, rows
