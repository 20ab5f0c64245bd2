"""The hand-made levels' exported Kinetix JSON files: writing them and checking them against the designs.

The command line is `python -m engine.levels.handmade.build` (see there). A file matches its design when the
design passes `validate_scene` and loading the file gives back the built `Level` bit for bit.
"""

from __future__ import annotations

import argparse
import sys

import jax
import numpy as np

from impulse.engine.levels import handmade
from impulse.engine.levels.kinetix_json import LevelFileError, load_kinetix_level, save_kinetix_level
from impulse.engine.levels.level import Level
from impulse.engine.physics.validate import validate_scene


def level_differences(a: Level, b: Level) -> list[str]:
    """Names of the leaves where two levels differ (shape, dtype or any value; NaN equals NaN)."""
    paths_a = jax.tree_util.tree_flatten_with_path(a)[0]
    leaves_b = jax.tree.leaves(b)
    if len(paths_a) != len(leaves_b):
        return ["tree structure"]
    found = []
    for (path, x), y in zip(paths_a, leaves_b, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
            found.append(jax.tree_util.keystr(path))
    return found


def check(name: str) -> list[str]:
    """Every problem with one level's design and its exported file (empty when all is well)."""
    entry = handmade.LEVELS[name]
    level = handmade.build(name)
    problems = [f"design: {p}" for p in validate_scene(level.state)]
    if not entry.path.exists():
        return problems + [f"{entry.path.name} missing (run python -m engine.levels.handmade.build)"]
    try:
        loaded = load_kinetix_level(entry.path, entry.sizes).level
    except LevelFileError as err:
        return problems + [str(err)]
    differ = level_differences(level, loaded)
    if differ:
        problems.append(f"{entry.path.name} differs from the design in {', '.join(differ)}")
    return problems


def export(name: str) -> None:
    entry = handmade.LEVELS[name]
    save_kinetix_level(entry.path, entry.builder(entry.sizes), entry.sizes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m engine.levels.handmade.build",
        description="Export the hand-made levels as Kinetix JSON files next to their designs, then check them.",
    )
    parser.add_argument("--check", action="store_true", help="only check the files, write nothing")
    parser.add_argument("names", nargs="*", help="levels to export or check (default: all)")
    args = parser.parse_args(argv)
    names = args.names or handmade.names()
    unknown = [n for n in names if n not in handmade.LEVELS]
    if unknown:
        parser.error(f"unknown level(s) {', '.join(unknown)}; available: {', '.join(handmade.names())}")
    failed = 0
    for name in names:
        if not args.check:
            export(name)
        problems = check(name)
        entry = handmade.LEVELS[name]
        status = "ok" if not problems else "FAILED"
        print(f"{name:24s} {entry.size.upper()}  {status}  {entry.path.name}")
        for problem in problems:
            print(f"    {problem}")
        failed += bool(problems)
    if failed:
        print(f"{failed} of {len(names)} level(s) failed", file=sys.stderr)
    return 1 if failed else 0
