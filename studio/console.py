"""The studio's line to a running run's curriculum service: the Curriculum page's buffer table and thumbnails, its
knobs, and the editor's "Send to run", all asked over the run's bus as the operator role (the only role a router
lets ask them) through `curriculum.client`.

`impulse studio --run RUN_DIR` builds the link from the run's configuration (`deploy.commands.studio`), since the
studio cannot read run configurations itself; `studio.app` serves it under `/api/curriculum` and `/api/inject`.
Each request opens a short session and closes it, so a run that stops or restarts between two requests is found
again; a dead run is a clear error in the page, never a stuck server.
"""

from __future__ import annotations

import json
import math
import os
import threading
from collections import OrderedDict
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
"""Buffer thumbnails kept in memory (by level id), newest first; a level that left the buffer ages out."""


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
        self._thumbnails: OrderedDict[str, bytes] = OrderedDict()
        self._lock = threading.Lock()

    def _client(self) -> CurriculumClient:
        return CurriculumClient(self.bus, self.run, f"studio-{os.getpid()}", self.timeout_s)

    def inject(self, document: dict[str, Any]) -> dict[str, Any]:
        """Send a Kinetix level-file object into the buffer: `{"ok": true, "slot", "level_id", "evicted"}`, or
        `{"ok": false, "error"}` with the service's reason; `CurriculumUnreachable` when it could not be asked."""
        with self._client() as client:
            return client.inject(document)

    def knobs(self, assignments: list[str] | None = None) -> dict[str, Any]:
        """The live knobs (`{"ok", "method", "knobs"}`), after `assignments` ("replay_prob=0.8", ...) when given,
        checked by the service as for `impulse curriculum set`; `{"ok": false, "error"}` when refused,
        `CurriculumUnreachable` when it could not be asked."""
        with self._client() as client:
            return client.knobs(assignments)

    def buffer(self, top: int) -> dict[str, Any]:
        """The buffer's report (`curriculum.stats.inspect_report`: summary, histograms, live knobs) with its
        `top` levels by score as rows whose `level_id` and `parent_id` are hexadecimal strings (a browser's
        numbers cannot hold 64 bits) and whose `origin` says how the level came; their thumbnails are drawn
        now and served by `thumbnail`. Raises `CurriculumUnreachable`, or `CurriculumRefused` with the service's
        reason."""
        report, levels = self._best(top)
        for row, level in zip(report.get("top", []), levels, strict=True):
            row["level_id"] = f"{int(row['level_id']):016x}"
            row["parent_id"] = f"{int(row['parent_id']):016x}"
            row["origin"] = f"mutated, generation {row['generation']}" if row.get("generation", 0) > 0 else "new"
            png = png_bytes(render_level(level, scale=THUMBNAIL_SCALE))
            with self._lock:
                self._thumbnails[row["level_id"]] = png
                self._thumbnails.move_to_end(row["level_id"])
        with self._lock:
            while len(self._thumbnails) > THUMBNAILS_KEPT:
                self._thumbnails.popitem(last=False)
        return json_ready({"run": self.run, **report})

    def thumbnail(self, level_id: str) -> bytes:
        """The PNG of a level the last `buffer` calls listed; `UnknownLevel` for any other."""
        with self._lock:
            png = self._thumbnails.get(level_id)
        if png is None:
            raise UnknownLevel(f"no thumbnail of buffer level {level_id!r}: refresh the curriculum page")
        return png

    def snapshot(self, folder: Path, top: int) -> int:
        """Write the buffer's `top` levels by score into `folder` as Kinetix level files named
        `<rank>_<level id>` (the studio's gallery set of the run), in place of the files a previous snapshot
        wrote; how many. Raises `CurriculumUnreachable`, or `CurriculumRefused` with the service's reason."""
        report, levels = self._best(top)
        rows = report.get("top", [])
        for old in folder.glob("*.json"):
            old.unlink()
        for rank, (row, level) in enumerate(zip(rows, levels, strict=True), start=1):
            document = level_to_json_dict(level, self.sizes, self.env_params.sim, self.spec.frame_skip,
                                          self.spec.solver)
            (folder / f"{rank:03d}_{int(row['level_id']):016x}.json").write_text(json.dumps(document))
        return len(levels)

    def _best(self, top: int) -> tuple[dict[str, Any], list[Level]]:
        """The service's inspect report of its `top` levels by score, and those levels (in the report's order)."""
        with self._client() as client:
            reply = client.inspect(top, levels=True)
        if reply.error is not None:
            raise CurriculumRefused(f"the curriculum service refused: {reply.error}")
        count = len(reply.report.get("top", []))
        if count == 0:
            return reply.report, []
        if not reply.arrays:
            raise CurriculumRefused("the curriculum service sent its report without the levels")
        template: Level = jax.eval_shape(lambda key: sample_random_level(key, self.sizes), jax.random.PRNGKey(0))
        arrays = {name: np.asarray(values) for name, values in reply.arrays.items()}
        levels = [tree_from_arrays({name: values[i] for name, values in arrays.items()}, template)
                  for i in range(count)]
        return reply.report, levels
