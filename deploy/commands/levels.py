"""`impulse levels`: validate, show, render and convert level files (Kinetix JSON, also Impulse's own format).

Exit status: 0 when everything
worked, 1 when a file is invalid or cannot be processed (every problem is printed), 2 for usage errors.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax

from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.progress import Heartbeat
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.checks import unsolvable_reasons
from impulse.engine.levels.kinetix_json import (
    LevelFileError,
    level_file_problems,
    load_kinetix_level,
    save_kinetix_level,
)
from impulse.engine.levels.level import stack_levels
from impulse.engine.levels.summary import describe_level
from impulse.engine.physics.sizes import SIZE_NAMES, size_preset
from impulse.engine.physics.validate import validate_scene
from impulse.learner.evaluate import play_episodes
from impulse.monitor.png import render_level, save_png
from impulse.monitor.video import DEFAULT_SCALE, check_video_path, write_episodes_video

SLOW_ACTIONS = {"render": "levels render: loading the levels and drawing them (JAX compiles the first time)",
                "convert": "levels convert: loading, checking and resizing the level (JAX compiles the first time)"}
"""The actions that show a heartbeat while they work (`deploy.runtime.progress.Heartbeat`)."""


def run(args: argparse.Namespace, _config: object) -> int:
    action = getattr(args, "levels_action", None)
    if action is None:
        args.levels_parser.print_usage(sys.stderr)
        print("impulse levels: choose an action: validate, show, render or convert", file=sys.stderr)
        return EXIT_USAGE
    act = {"validate": _validate, "show": _show, "render": _render, "convert": _convert}[action]
    if action not in SLOW_ACTIONS:
        return act(args)
    with Heartbeat(SLOW_ACTIONS[action]):  # they load, check and play levels: tens of seconds on a CPU at first
        return act(args)


def _sizes(name: str | None):
    return size_preset(name) if name else None


def _level_files(paths: list[Path]) -> tuple[list[Path], list[str]]:
    """(the files to check, one "PATH: problem" line per path that names nothing to check). Folders are searched
    for *.json files (folders named like one are skipped); anything else that exists is checked as a file, so a
    pipe, a device or an unreadable file is reported by the loader, naming it."""
    files, missing = [], []
    for path in paths:
        if path.is_dir():
            found = sorted(file for file in path.rglob("*.json") if not file.is_dir())
            if not found:
                missing.append(f"{path}: no .json files in this folder")
            files += found
        elif path.exists():
            files.append(path)
        else:
            missing.append(f"{path}: no such file or folder")
    return files, missing


def _validate(args: argparse.Namespace) -> int:
    """Every problem of every file; a valid file that cannot be solved (`engine.levels.checks`) is still valid (it
    does not change the exit status), but its line says why it cannot be solved."""

    files, missing = _level_files(args.paths)
    for line in missing:
        print(f"error  {line}")
    sizes = _sizes(args.size)
    invalid = unsolvable = 0
    for file in files:
        problems = level_file_problems(file, sizes)
        if problems:
            invalid += 1
            print(f"INVALID  {file}")
            for problem in problems:
                print(f"    {problem}")
            continue
        loaded = load_kinetix_level(file, sizes, validate=False)  # valid: it loads (validated just now)
        reasons = unsolvable_reasons(loaded.level, loaded.sizes)
        if reasons:
            unsolvable += 1
            print(f"ok, but cannot be solved: {'; '.join(reasons)}  {file}")
        else:
            print(f"ok       {file}")
    total = len(files)
    unfound = f", {len(missing)} paths with no level file" if missing else ""
    unsolved = f" ({unsolvable} of them cannot be solved)" if unsolvable else ""
    print(f"{total - invalid} of {total} level files valid{unsolved}{unfound}")
    return EXIT_FAILED if invalid or missing else 0


def _load(path: Path, size: str | None, validate: bool = True):
    try:
        return load_kinetix_level(path, _sizes(size), validate=validate)
    except LevelFileError as err:
        print(f"impulse levels: {err}", file=sys.stderr)
        return None


def _show(args: argparse.Namespace) -> int:
    loaded = _load(args.path, args.size, validate=False)
    if loaded is None:
        return EXIT_FAILED
    print(f"level: {args.path}")
    print(describe_level(loaded.level, loaded.sizes, file_sizes=loaded.file_sizes, params=loaded.params,
                         frame_skip=loaded.frame_skip))
    problems = validate_scene(loaded.state)
    for problem in problems:
        print(f"problem: {problem}")
    return EXIT_FAILED if problems else 0


def _render(args: argparse.Namespace) -> int:
    if args.scale is not None and not args.scale > 0:
        print(f"impulse levels render: --scale must be positive, got {args.scale}", file=sys.stderr)
        return EXIT_USAGE
    if args.video is not None:
        return _render_video(args)
    if len(args.paths) != 1:
        print("impulse levels render: a PNG draws one level file; --video plays several", file=sys.stderr)
        return EXIT_USAGE
    [path] = args.paths
    loaded = _load(path, None, validate=False)
    if loaded is None:
        return EXIT_FAILED
    image = render_level(loaded.level, scale=1.0 if args.scale is None else args.scale)
    try:
        save_png(image, args.output)
    except OSError as err:
        print(f"impulse levels render: cannot write {args.output}: {err}", file=sys.stderr)
        return EXIT_FAILED
    print(f"wrote {args.output} ({image.shape[1]} x {image.shape[0]} pixels)")
    return 0


def _render_video(args: argparse.Namespace) -> int:
    """`levels render --video`: the levels played with no-op actions (`learner.evaluate.play_episodes`) and drawn
    as `impulse eval --video` draws episodes (`monitor.video.write_episodes_video`)."""

    try:
        check_video_path(args.video)
    except ValueError as err:
        print(f"impulse levels render: --video: {err}", file=sys.stderr)
        return EXIT_USAGE
    if args.steps < 1:
        print(f"impulse levels render: --steps must be at least 1, got {args.steps}", file=sys.stderr)
        return EXIT_USAGE
    files, missing = _level_files(args.paths)
    for line in missing:
        print(f"impulse levels render: {line}", file=sys.stderr)
    if missing:
        return EXIT_FAILED
    try:
        own = [load_kinetix_level(file, validate=False).sizes for file in files]
    except LevelFileError as err:
        print(f"impulse levels render: {err}", file=sys.stderr)
        return EXIT_FAILED
    fitting = [name for name in SIZE_NAMES if all(sizes.fits_in(size_preset(name)) for sizes in own)]
    size = args.size or (fitting[0] if fitting else None)
    if size is None:
        print("impulse levels render: these levels fit no size class together (s, m, l)", file=sys.stderr)
        return EXIT_FAILED
    levels = []
    for file in files:
        loaded = _load(file, size)
        if loaded is None:
            return EXIT_FAILED
        levels.append(loaded.level)
    spec = EnvSpec(sizes=size_preset(size), max_timesteps=args.steps)
    episodes = play_episodes(None, None, spec, EnvParams(), stack_levels(levels), jax.random.PRNGKey(0))
    try:
        write_episodes_video(args.video, [str(file) for file in files], episodes,
                             scale=DEFAULT_SCALE if args.scale is None else args.scale)
    except OSError as err:
        print(f"impulse levels render: cannot write {args.video}: {err}", file=sys.stderr)
        return EXIT_FAILED
    longest = int(episodes.first.sum(axis=0).max())
    print(f"wrote {args.video}: {len(files)} level{'s' * (len(files) > 1)} played with no-op actions for up to "
          f"{longest} steps (size {size.upper()})")
    return 0


def _convert(args: argparse.Namespace) -> int:
    loaded = _load(args.source, args.size)
    if loaded is None:
        return EXIT_FAILED
    try:
        save_kinetix_level(args.target, loaded.level, loaded.sizes, loaded.params, loaded.frame_skip, loaded.options)
    except OSError as err:
        print(f"impulse levels convert: cannot write {args.target}: {err}", file=sys.stderr)
        return EXIT_FAILED
    print(f"wrote {args.target} (size {args.size.upper()})")
    return 0
