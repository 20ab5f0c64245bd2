"""Named sets of levels, resolved into one batch of a given size: what `env.levels` in a config means.

- "handmade": our own hand-made levels (`engine.levels.handmade`) that fit the size, the default evaluation set;
  "handmade:NAME,NAME" picks some of them by name.
- "kinetix:s", "kinetix:m", "kinetix:l" (Kinetix's hand-made sets of that size, 10 / 24 / 40 levels, as its
  `eval/{s,m,l}.yaml`) and "kinetix:all" (all 74), read from Kinetix's level folder (`kinetix_levels_root`) and
  named like Kinetix's ("s/h0_weak_thrust");
- a level file (".json"), a folder of them (searched recursively), or a glob pattern ("levels/**/h*.json"), each
  loaded into the size;
- "random" is not a fixed set: trainers sample random levels on the device instead (see
  `engine.levels.generator`), so `load_level_set` rejects it with a message saying so.
"""

from __future__ import annotations

import glob
import importlib.util
import os
import re
from pathlib import Path

from impulse.engine.levels.kinetix_json import LevelFileError, load_kinetix_level
from impulse.engine.levels.level import Level, stack_levels
from impulse.engine.physics.sizes import SceneSizes

RANDOM = "random"
HANDMADE = "handmade"
KINETIX = "kinetix"
KINETIX_SETS = {"s": ("s",), "m": ("m",), "l": ("l",), "all": ("s", "m", "l")}
KINETIX_LEVELS_ENV = "IMPULSE_KINETIX_LEVELS"
GLOB_CHARACTERS = frozenset("*?[")


class LevelSetError(ValueError):
    """A level set cannot be resolved (unknown name, empty folder, levels that do not fit the size)."""


def _handmade(names: list[str] | None, sizes: SceneSizes) -> tuple[list[str], list[Level]]:
    from impulse.engine.levels import handmade  # imported here: building the designs costs time only when used

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


def _level_files_under(folder: Path, pattern: str = "*.json", recursive: bool = True) -> list[Path]:
    """The `pattern` files in `folder`, sorted; folders that happen to be named like one are not level files."""
    found = folder.rglob(pattern) if recursive else folder.glob(pattern)
    return sorted(file for file in found if not file.is_dir())


def _files(path: Path) -> list[Path]:
    if path.is_dir():
        files = _level_files_under(path)
        if not files:
            raise LevelSetError(f"no .json level files under {path}")
        return files
    if path.exists():  # a file, or something else (a pipe, a device) that the loader refuses, naming it
        return [path]
    raise LevelSetError(
        f"level set {str(path)!r} is neither {HANDMADE!r}, {RANDOM!r}, a level file nor a folder of level files"
    )


def kinetix_levels_root() -> Path:
    """Kinetix's level folder (holding s/, m/ and l/): `$IMPULSE_KINETIX_LEVELS`, else the `levels` folder of an
    installed `kinetix` package (`pip install kinetix-env`), else a `shared/kinetix-levels` folder beside this
    checkout. Kinetix's files are not part of Impulse; raises LevelSetError saying how to provide them."""
    candidates = []
    if os.environ.get(KINETIX_LEVELS_ENV):
        candidates.append(Path(os.environ[KINETIX_LEVELS_ENV]).expanduser())
    else:
        spec = importlib.util.find_spec(KINETIX)
        if spec is not None and spec.submodule_search_locations:
            candidates += [Path(location) / "levels" for location in spec.submodule_search_locations]
        candidates.append(Path(__file__).resolve().parents[3] / "shared" / "kinetix-levels")
    for candidate in candidates:
        if (candidate / "s").is_dir():
            return candidate
    raise LevelSetError(f"Kinetix's level files were not found (looked in {', '.join(map(str, candidates))}): set "
                        f"{KINETIX_LEVELS_ENV} to the folder holding s/, m/ and l/ (kinetix/levels in a Kinetix "
                        "checkout or an installed kinetix-env)")


def _kinetix_files(which: str) -> list[tuple[str, Path]]:
    if which not in KINETIX_SETS:
        raise LevelSetError(f"unknown Kinetix level set {KINETIX}:{which}; known: "
                            f"{', '.join(f'{KINETIX}:{name}' for name in KINETIX_SETS)}")
    root = kinetix_levels_root()
    files = [(f"{size}/{file.stem}", file) for size in KINETIX_SETS[which]
             for file in _level_files_under(root / size, recursive=False)]
    if not files:
        raise LevelSetError(f"no level files in {root} for {KINETIX}:{which}")
    return files


def _glob_files(pattern: str) -> list[tuple[str, Path]]:
    files = sorted(Path(match) for match in glob.glob(os.path.expanduser(pattern), recursive=True)
                   if match.endswith(".json") and not os.path.isdir(match))
    if not files:
        raise LevelSetError(f"no .json level files match {pattern!r}")
    common = Path(os.path.commonpath([file.parent for file in files]))
    return [(str(file.relative_to(common)).removesuffix(".json"), file) for file in files]


def kinetix_group(name: str) -> str:
    """The group Kinetix aggregates a hand-made level's score into, e.g. "l/mjc_hopper" -> "l_mjc" and
    "s/h4_thrust_aim" -> "s_handmade": the size, then the file name's first word without digits ("h" meaning
    hand-made)."""
    size, _, stem = name.rpartition("/")
    prefix = re.sub(r"\d", "", stem.split("_")[0]) or stem
    return f"{size}_{'handmade' if prefix == 'h' else prefix}"


MAX_LISTED_PROBLEMS = 20
"""How many problems a `LevelSetError` for unloadable files lists before summing up the rest."""


def _unloadable(source: str, total: int, failures: list[LevelFileError]) -> LevelSetError:
    """The error for a set whose files do not all load: a set of one file gives that file's error as it is;
    a larger set says how many files failed, then one line per problem, each starting with the file's path."""
    if total == 1:
        return LevelSetError(str(failures[0]))
    lines = [f"{failure.path}: {problem}" for failure in failures for problem in failure.problems]
    if len(lines) > MAX_LISTED_PROBLEMS:
        lines = [*lines[:MAX_LISTED_PROBLEMS], f"... and {len(lines) - MAX_LISTED_PROBLEMS} more problems"]
    listed = "\n  ".join(lines)
    return LevelSetError(f"level set {source!r}: {len(failures)} of {total} level files cannot be loaded:\n  {listed}")


def load_level_set(source: str, sizes: SceneSizes) -> tuple[list[str], Level]:
    """(names, batch of levels [K]) for a level-set string, every level in `sizes`.

    Raises `LevelSetError` when the set cannot be resolved or any of its files does not load; every file that
    fails is named with its problems (all of them, not only the first file's, so one run finds every bad file)."""
    if source == RANDOM:
        raise LevelSetError("'random' levels are sampled by the trainer, not loaded from a set")
    if source == HANDMADE or source.startswith(HANDMADE + ":"):
        picked = source.partition(":")[2]
        names, levels = _handmade([n for n in picked.split(",") if n] or None, sizes)
    else:
        if source.startswith(KINETIX + ":"):
            named = _kinetix_files(source.partition(":")[2])
        elif GLOB_CHARACTERS & set(source):
            named = _glob_files(source)
        else:
            files = _files(Path(source))
            named = [(file.stem if len(files) == 1 else str(file.relative_to(source)).removesuffix(".json"), file)
                     for file in files]
        names, levels, failures = [], [], []
        for name, file in named:
            try:
                levels.append(load_kinetix_level(file, sizes).level)
            except LevelFileError as err:
                failures.append(err)
                continue
            names.append(name)
        if failures:
            raise _unloadable(source, len(named), failures) from failures[0]
    if not levels:
        raise LevelSetError(f"level set {source!r} has no level that fits the configured size")
    return names, stack_levels(levels)
