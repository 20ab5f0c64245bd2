"""Named sets of levels, resolved into one batch of a given size: what `env.levels` in a config means.

- "handmade": our own hand-made levels (`engine.levels.handmade`) that fit the size, the default evaluation set;
  "handmade:NAME,NAME" picks some of them by name.
- a level file (".json") or a folder of them (searched recursively), each loaded into the size;
- "random" is not a fixed set: trainers sample random levels on the device instead (see
  `engine.levels.generator`), so `load_level_set` rejects it with a message saying so.
"""

from __future__ import annotations

from pathlib import Path

from engine.levels.kinetix_json import LevelFileError, load_kinetix_level
from engine.levels.level import Level, stack_levels
from engine.physics.sizes import SceneSizes

RANDOM = "random"
HANDMADE = "handmade"


class LevelSetError(ValueError):
    """A level set cannot be resolved (unknown name, empty folder, levels that do not fit the size)."""


def _handmade(names: list[str] | None, sizes: SceneSizes) -> tuple[list[str], list[Level]]:
    from engine.levels import handmade  # imported here: building the designs costs time only when used

    available = handmade.names()
    if names:
        unknown = [n for n in names if n not in available]
        if unknown:
            raise LevelSetError(f"unknown hand-made level(s) {', '.join(unknown)}; available: {', '.join(available)}")
        chosen = names
    else:
        chosen = [n for n in available if handmade.size_of(n).fits_in(sizes)]
    levels = []
    for name in chosen:
        if not handmade.size_of(name).fits_in(sizes):
            raise LevelSetError(f"hand-made level {name} is too large for the configured size")
        levels.append(handmade.build(name, sizes))
    return chosen, levels


def _files(path: Path) -> list[Path]:
    if path.is_dir():
        files = sorted(path.rglob("*.json"))
        if not files:
            raise LevelSetError(f"no .json level files under {path}")
        return files
    if path.is_file():
        return [path]
    raise LevelSetError(
        f"level set {str(path)!r} is neither {HANDMADE!r}, {RANDOM!r}, a level file nor a folder of level files"
    )


def load_level_set(source: str, sizes: SceneSizes) -> tuple[list[str], Level]:
    """(names, batch of levels [K]) for a level-set string, every level in `sizes`."""
    if source == RANDOM:
        raise LevelSetError("'random' levels are sampled by the trainer, not loaded from a set")
    if source == HANDMADE or source.startswith(HANDMADE + ":"):
        picked = source.partition(":")[2]
        names, levels = _handmade([n for n in picked.split(",") if n] or None, sizes)
    else:
        files = _files(Path(source))
        names, levels = [], []
        for file in files:
            try:
                levels.append(load_kinetix_level(file, sizes).level)
            except LevelFileError as err:
                raise LevelSetError(str(err)) from err
            names.append(file.stem if len(files) == 1 else str(file.relative_to(source)).removesuffix(".json"))
    if not levels:
        raise LevelSetError(f"level set {source!r} has no level that fits the configured size")
    return names, stack_levels(levels)
