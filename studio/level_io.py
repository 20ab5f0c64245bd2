"""Levels sent by the browser: checked, loaded and saved with the engine's own level-file code.

The page holds a level as the JSON object of a Kinetix level file (what `GET /api/level/...` returns). A document
posted back is written to a temporary file and read by `engine.levels.kinetix_json` exactly as a file on disk is,
so the studio accepts what `impulse levels validate` accepts and refuses what it refuses, with the same messages;
there is no second reader. Saving writes the normalised Kinetix format (`save_kinetix_level`), so a level saved
here loads in Kinetix and in every Impulse command. A file that cannot be written (a full disk, a read-only
folder, an I/O error) is a `StorageError` naming the file and the free space on its disk; a save writes a
temporary file beside the level and renames it into place (`save_kinetix_level`), so a failed save leaves no
partial file.
"""

from __future__ import annotations

import json
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

from impulse.engine.levels.kinetix_json import (
    KinetixLevel,
    LevelFileError,
    level_file_problems,
    level_to_json_dict,
    load_kinetix_level,
    save_kinetix_level,
)
from impulse.engine.levels.level import Level
from impulse.engine.physics.sizes import SceneSizes, size_preset

LEVEL_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,99}")
"""A saved level's name: its file is `<name>.json` in the levels folder (no folders, nothing hidden)."""


class LevelInputError(ValueError):
    """A level (or a request about one) that cannot be used; `problems` lists every problem found, each naming the
    field, as `impulse levels validate` prints them."""

    def __init__(self, message: str, problems: list[str] | None = None):
        super().__init__(message)
        self.message = message
        self.problems = list(problems or [])

    def __str__(self) -> str:
        return self.message if not self.problems else f"{self.message}: " + "; ".join(self.problems)


class StorageError(Exception):
    """A level file (or the temporary copy a check reads) that could not be written: the message names the file,
    the system's reason and the free space where it was going; `errno` is the system's error number."""

    def __init__(self, path: Path, err: OSError):
        super().__init__(f"cannot write {path}: {err.strerror or err} ({_free_space(path)})")
        self.path = path
        self.errno = err.errno


def _free_space(path: Path) -> str:
    """The free space on the disk that holds `path` (or its nearest existing folder), as a phrase."""
    for folder in (path, *path.parents):
        if folder.exists():
            try:
                return f"{shutil.disk_usage(folder).free / 1e6:,.1f} MB free on its disk"
            except OSError:
                break
    return "free space unknown"


def parse_size(size: Any) -> SceneSizes | None:
    """The Kinetix size called `size` ("s", "m", "l"), or None for "the level's own size"."""
    if size in (None, ""):
        return None
    if not isinstance(size, str):
        raise LevelInputError(f"size must be \"s\", \"m\" or \"l\", got {json.dumps(size)}")
    try:
        return size_preset(size)
    except ValueError as err:
        raise LevelInputError(str(err)) from None


def _with_file(document: Any, use):
    """`use(path)` with `document` written as a level file to a temporary folder (removed afterwards)."""
    if not isinstance(document, dict):
        raise LevelInputError(f"a level must be a JSON object (a Kinetix level file), got {type(document).__name__}")
    text = json.dumps(document)
    try:
        scratch = tempfile.TemporaryDirectory(prefix="impulse-studio-")
    except OSError as err:
        raise StorageError(Path(tempfile.gettempdir()), err) from None
    with scratch as folder:
        path = Path(folder) / "level.json"
        try:
            path.write_text(text)
        except OSError as err:
            raise StorageError(path, err) from None
        return use(path)


def level_problems(document: Any, sizes: SceneSizes | None = None) -> list[str]:
    """Every problem `impulse levels validate [--size]` finds in the document (format, fit into `sizes`, scene);
    empty when it is valid."""
    return _with_file(document, lambda path: level_file_problems(path, sizes))


def load_document(
    document: Any, sizes: SceneSizes | None = None, *, validate: bool = True, compact: bool = False
) -> KinetixLevel:
    """The document loaded as a level file (into `sizes`, else its own size; with `compact`, cut to the slots it
    uses when it is larger than `sizes`); `LevelInputError` with every problem when it does not load (or, with
    `validate`, holds an invalid scene)."""

    def load(path: Path) -> KinetixLevel:
        try:
            return load_kinetix_level(path, sizes, validate=validate, compact=compact)
        except LevelFileError as err:
            raise LevelInputError("the level is not valid", err.problems) from None

    return _with_file(document, load)


def load_file(path: Path, sizes: SceneSizes | None = None, *, validate: bool = False) -> KinetixLevel:
    """A level file from a level set, `LevelInputError` naming the file's problems if it does not load."""
    try:
        return load_kinetix_level(path, sizes, validate=validate)
    except LevelFileError as err:
        raise LevelInputError(f"{path.name} does not load", err.problems) from None


def level_document(loaded: KinetixLevel, level: Level | None = None) -> dict[str, Any]:
    """`level` (default: the loaded one) as a Kinetix level-file object, with the loaded file's physics settings
    (params, frame skip, solver options) and sizes."""
    return level_to_json_dict(loaded.level if level is None else level, loaded.sizes, loaded.params,
                              loaded.frame_skip, loaded.options)


def check_name(name: Any) -> str:
    """A valid saved-level name, else `LevelInputError` saying what names look like."""
    if not isinstance(name, str) or not LEVEL_NAME.fullmatch(name.removesuffix(".json")):
        raise LevelInputError(f"a level name is 1 to 100 letters, digits, '_', '-' or '.', starting with a letter "
                              f"or digit, got {json.dumps(name)}")
    return name.removesuffix(".json")


def save_document(document: Any, name: Any, folder: Path, size: Any = None) -> tuple[Path, KinetixLevel]:
    """Check the document as `impulse levels validate --size` does and save it as `folder/<name>.json` (in `size`,
    else its own size). Returns (the file, the level as saved); `LevelInputError` with every problem, and nothing
    written, when it is invalid; `StorageError`, and nothing written, when the file cannot be written."""
    name = check_name(name)
    sizes = parse_size(size)
    problems = level_problems(document, sizes)
    if problems:
        raise LevelInputError("the level is not valid", problems)
    loaded = load_document(document, sizes)
    path = folder / f"{name}.json"
    try:
        save_kinetix_level(path, loaded.level, loaded.sizes, loaded.params, loaded.frame_skip, loaded.options)
    except OSError as err:  # the temporary file is removed: no partial level is left
        raise StorageError(path, err) from None
    return path, loaded
