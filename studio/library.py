"""The level sets the studio shows: which sets there are, their files, a summary of each level and its thumbnail.

Sets, by id: "handmade" (our hand-made levels' exported files), "kinetix:s", "kinetix:m", "kinetix:l" (Kinetix's
hand-made sets, where its level folder is found: `engine.levels.sets.kinetix_levels_root`), "saved" (the folder
the studio saves into, `--levels-dir`) and every folder, file or glob pattern given on the command line (its id is
the text as given). Every level is a file, read with the engine's loader; a level is named within its set (the
file's path relative to the set's folder, without ".json"), and only files a set lists can be opened, so a request
never names an arbitrary path.

Summaries and thumbnails (drawn by the PNG renderer, `monitor.png`) are cached by file, modification time and size,
so a level edited on disk is read again.
"""

from __future__ import annotations

import glob
import io
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from impulse.engine.levels import handmade
from impulse.engine.levels.sets import GLOB_CHARACTERS, LevelSetError, kinetix_levels_root
from impulse.engine.levels.summary import size_class
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState
from impulse.monitor.png import render_level
from impulse.studio.level_io import LevelInputError, load_file

HANDMADE = "handmade"
SAVED = "saved"
KINETIX_SIZES = ("s", "m", "l")
THUMBNAIL_SCALE = 0.32
"""Thumbnails are 160 x 160 pixels (Kinetix's 500-pixel screen at this scale)."""


class UnknownLevel(LookupError):
    """A set or level name the library does not list."""


@dataclass(frozen=True)
class LevelSet:
    """One set: its id, a title for the page, and why it is unavailable (None when it is available)."""

    id: str
    title: str
    unavailable: str | None = None


def _json_files(folder: Path) -> list[tuple[str, Path]]:
    files = sorted(file for file in folder.rglob("*.json") if file.is_file())
    return [(file.relative_to(folder).as_posix().removesuffix(".json"), file) for file in files]


def level_counts(state: SimState, sizes: SceneSizes) -> dict[str, int]:
    """Active shapes (not counting the arena), polygons, circles, joints and thrusters of a scene of `sizes`."""
    active = np.asarray(state.bodies.active, bool)
    num_polygons = sizes.num_polygons
    polygons = int(active[sizes.num_static_polygons:num_polygons].sum())
    circles = int(active[num_polygons:].sum())
    return {"shapes": polygons + circles, "polygons": polygons, "circles": circles,
            "joints": int(np.asarray(state.joints.active).sum()),
            "thrusters": int(np.asarray(state.thrusters.active).sum())}


def png_bytes(image: np.ndarray) -> bytes:
    """An [H, W, 3] uint8 image as PNG file bytes."""
    out = io.BytesIO()
    Image.fromarray(np.asarray(image, np.uint8), "RGB").save(out, format="PNG")
    return out.getvalue()


class Library:
    """The sets of one studio: hand-made, Kinetix's, the saved folder, the command line's `sources` and `folders`."""

    def __init__(self, levels_dir: Path, sources: tuple[str, ...] = (),
                 folders: dict[str, tuple[str, Path]] | None = None):
        self.levels_dir = Path(levels_dir)
        self.sources = tuple(sources)
        self.folders = dict(folders or {})
        """Sets kept in folders that the studio writes itself (a running curriculum's buffer): id -> (title,
        folder)."""
        self._lock = threading.Lock()
        self._summaries: dict[tuple, dict[str, Any]] = {}
        self._thumbnails: dict[tuple, bytes] = {}

    def sets(self) -> list[LevelSet]:
        """Every set, available or not (a missing Kinetix folder says how to provide it)."""
        found = [LevelSet(HANDMADE, "Impulse hand-made levels")]
        try:
            root = kinetix_levels_root()
            missing = None
        except LevelSetError as err:
            root, missing = None, str(err)
        for size in KINETIX_SIZES:
            if root is not None and not (root / size).is_dir():
                missing = f"no folder {root / size}"
            found.append(LevelSet(f"kinetix:{size}", f"Kinetix hand-made, size {size.upper()}", missing))
        found.append(LevelSet(SAVED, f"Saved in {self.levels_dir}"))
        found += [LevelSet(source, source) for source in self.sources]
        return found + [LevelSet(set_id, title) for set_id, (title, _) in self.folders.items()]

    def files(self, set_id: str) -> list[tuple[str, Path]]:
        """(name, file) of every level of a set, sorted by name; `UnknownLevel` for a set it does not have."""
        if set_id == HANDMADE:
            return [(name, handmade.level_file(name)) for name in handmade.names()]
        if set_id.startswith("kinetix:") and set_id.partition(":")[2] in KINETIX_SIZES:
            try:
                folder = kinetix_levels_root() / set_id.partition(":")[2]
            except LevelSetError as err:
                raise UnknownLevel(str(err)) from None
            return [(file.stem, file) for file in sorted(folder.glob("*.json")) if file.is_file()]
        if set_id == SAVED:
            return _json_files(self.levels_dir) if self.levels_dir.is_dir() else []
        if set_id in self.sources:
            return self._source_files(set_id)
        if set_id in self.folders:
            return _json_files(self.folders[set_id][1])
        raise UnknownLevel(f"no level set {set_id!r}; known: {', '.join(s.id for s in self.sets())}")

    @staticmethod
    def _source_files(source: str) -> list[tuple[str, Path]]:
        if GLOB_CHARACTERS & set(source):
            files = sorted(Path(match) for match in glob.glob(os.path.expanduser(source), recursive=True)
                           if match.endswith(".json") and os.path.isfile(match))
            if not files:
                return []
            common = Path(os.path.commonpath([file.parent for file in files]))
            return [(file.relative_to(common).as_posix().removesuffix(".json"), file) for file in files]
        path = Path(source).expanduser()
        if path.is_dir():
            return _json_files(path)
        return [(path.stem, path)] if path.is_file() else []

    def path(self, set_id: str, name: str) -> Path:
        """The file of level `name` in set `set_id`; `UnknownLevel` if the set does not list it."""
        for listed, path in self.files(set_id):
            if listed == name:
                return path
        raise UnknownLevel(f"no level {name!r} in set {set_id!r}")

    @staticmethod
    def _key(path: Path) -> tuple:
        stat = path.stat()
        return str(path.resolve()), stat.st_mtime_ns, stat.st_size

    def summary(self, set_id: str, name: str, path: Path) -> dict[str, Any]:
        """Name, size class, counts of shapes, joints and thrusters (or the problem that stops the file loading)."""
        key = self._key(path)
        with self._lock:
            cached = self._summaries.get(key)
        if cached is None:
            try:
                loaded = load_file(path)
                counts = level_counts(loaded.state, loaded.sizes)
                cached = {"size": size_class(loaded.file_sizes or loaded.sizes), **counts}
            except LevelInputError as err:
                cached = {"size": "?", "problem": str(err)}
            with self._lock:
                self._summaries[key] = cached
        return {"set": set_id, "name": name, **cached}

    def summaries(self, set_id: str) -> list[dict[str, Any]]:
        return [self.summary(set_id, name, path) for name, path in self.files(set_id)]

    def thumbnail(self, set_id: str, name: str) -> bytes:
        """The level's initial scene as a PNG (160 x 160 pixels), drawn by `monitor.png`."""
        path = self.path(set_id, name)
        key = self._key(path)
        with self._lock:
            cached = self._thumbnails.get(key)
        if cached is None:
            cached = png_bytes(render_level(load_file(path).level, scale=THUMBNAIL_SCALE))
            with self._lock:
                self._thumbnails[key] = cached
        return cached
