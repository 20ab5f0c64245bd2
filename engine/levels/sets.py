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

Levels that do not fit the size. A set of several levels ("handmade", "kinetix:...", a folder, a glob) keeps the
levels that fit and leaves the others out, saying so in one warning (logged at WARNING by this module) that names
every level left out and the size it needs: training, evaluation, `impulse launch` and anything else that loads a
set through `load_level_set` behave alike, and a run never plays fewer levels than its set holds without a word. A
level named on its own ("handmade:NAME", a single file) must fit: it is refused with an error naming it, and so is a
set of which no level fits.
"""

from __future__ import annotations

import glob
import importlib.util
import logging
import os
import re
from pathlib import Path

from impulse.engine.levels.kinetix_json import LevelDoesNotFit, LevelFileError, load_kinetix_level
from impulse.engine.levels.level import Level, stack_levels
from impulse.engine.levels.summary import describe_sizes, size_class
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes

log = logging.getLogger(__name__)

RANDOM = "random"
HANDMADE = "handmade"
KINETIX = "kinetix"
KINETIX_SETS = {"s": ("s",), "m": ("m",), "l": ("l",), "all": ("s", "m", "l")}
KINETIX_LEVELS_ENV = "IMPULSE_KINETIX_LEVELS"
GLOB_CHARACTERS = frozenset("*?[")


class LevelSetError(ValueError):
    """A level set cannot be resolved (unknown name, empty folder, levels that do not fit the size)."""


def size_name(sizes: SceneSizes) -> str:
    """How messages name a size: "s", "m" or "l" for Kinetix's sizes (as `env.size` takes them), else its slot
    counts."""
    name = size_class(sizes)
    return name.lower() if name != "custom" else describe_sizes(sizes)


def size_needed(sizes: SceneSizes) -> str:
    """The smallest of Kinetix's sizes that a level of slot counts `sizes` fits ("s", "m" or "l"), else the slot
    counts themselves (more than L has, or another arena)."""
    for name, preset in (("s", SIZE_S), ("m", SIZE_M), ("l", SIZE_L)):
        if sizes.fits_in(preset):
            return name
    return describe_sizes(sizes)


Skipped = list[tuple[str, str]]
"""Levels of a set that do not fit the size: (name, the size it needs)."""


def _handmade(names: list[str] | None, sizes: SceneSizes) -> tuple[list[str], list[Level], Skipped]:
    """(names, levels, skipped) of the hand-made set: all levels that fit `sizes` (the others skipped), or the
    ones named, each of which must fit."""
    from impulse.engine.levels import handmade  # imported here: building the designs costs time only when used

    available = handmade.names()
    if names:
        unknown = [n for n in names if n not in available]
        if unknown:
            raise LevelSetError(f"unknown hand-made level(s) {', '.join(unknown)}; available: {', '.join(available)}")
        too_large = [n for n in names if not handmade.size_of(n).fits_in(sizes)]
        if too_large:
            listed = ", ".join(f"{n} (needs {size_needed(handmade.size_of(n))})" for n in too_large)
            raise LevelSetError(f"hand-made level(s) {listed} too large for size {size_name(sizes)}")
        chosen, skipped = names, []
    else:
        chosen = [n for n in available if handmade.size_of(n).fits_in(sizes)]
        skipped = [(n, size_needed(handmade.size_of(n))) for n in available if n not in chosen]
    return chosen, [handmade.build(name, sizes) for name in chosen], skipped


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


def _left_out(skipped: Skipped) -> str:
    return ", ".join(f"{name} (needs {needs})" for name, needs in skipped)


def load_level_set(source: str, sizes: SceneSizes) -> tuple[list[str], Level]:
    """(names, batch of levels [K]) for a level-set string, every level in `sizes`.

    Levels of a larger size are left out of a set of several, with one warning naming each and the size it needs
    (the module docstring); a set of one level that does not fit, or of which none fits, is refused. Raises
    `LevelSetError` when the set cannot be resolved or any of its files does not load; every file that fails is
    named with its problems (all of them, not only the first file's, so one run finds every bad file)."""
    if source == RANDOM:
        raise LevelSetError("'random' levels are sampled by the trainer, not loaded from a set")
    if source == HANDMADE or source.startswith(HANDMADE + ":"):
        picked = source.partition(":")[2]
        names, levels, skipped = _handmade([n for n in picked.split(",") if n] or None, sizes)
    else:
        one_file = False
        if source.startswith(KINETIX + ":"):
            named = _kinetix_files(source.partition(":")[2])
        elif GLOB_CHARACTERS & set(source):
            named = _glob_files(source)
        else:
            files = _files(Path(source))
            one_file = not Path(source).is_dir()
            named = [(file.stem if len(files) == 1 else str(file.relative_to(source)).removesuffix(".json"), file)
                     for file in files]
        names, levels, failures, skipped = [], [], [], []
        for name, file in named:
            try:
                levels.append(load_kinetix_level(file, sizes).level)
            except LevelDoesNotFit as err:
                if one_file:
                    failures.append(err)
                else:
                    skipped.append((name, size_needed(err.needs)))
                continue
            except LevelFileError as err:
                failures.append(err)
                continue
            names.append(name)
        if failures:
            raise _unloadable(source, len(named), failures) from failures[0]
    total = len(names) + len(skipped)
    if not levels:
        if total == 1:
            raise LevelSetError(f"level set {source!r}: its one level, {_left_out(skipped)}, does not fit size "
                                f"{size_name(sizes)}")
        raise LevelSetError(f"level set {source!r}: none of its {total} levels fits size {size_name(sizes)}: "
                            f"{_left_out(skipped)}")
    if skipped:
        log.warning("level set %r: %d of %d levels do not fit size %s and are left out: %s", source, len(skipped),
                    total, size_name(sizes), _left_out(skipped))
    return names, stack_levels(levels)
