"""Which run a command works on: its configuration and its run directory, found one way for every command.

A command is given either a run directory (`--run RUN_DIR` for the services and the curriculum tools, `--resume
RUN_DIR` for `impulse train` and `impulse launch`), whose `config.toml` is read with the command line's
`key=value` overrides on top, or a configuration resolved from `--config FILE` and the overrides, whose `run_dir`
is the run directory. `--connect ENDPOINT` replaces `bus.connect` either way.

A new run that is refused before it trains (its update does not fit in memory, its levels do not load) takes back
the run directory it created (`create_run_dir`, `remove_unstarted_run`), so a failed try leaves no directory that
looks like a run but holds none; a directory that was there before, or that holds checkpoints, is never removed.
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from impulse.deploy.config import ConfigError, load_run_config, resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.learner.run_directory import holds_checkpoints


class RunSetupError(Exception):
    """The command line names no usable run; the message says why, for the person at the terminal."""


def open_run(config: RunConfig | None, *, run_dir: Path | None = None, toml: Path | None = None,
             overrides: Sequence[str] = (), connect: str | None = None) -> tuple[RunConfig, Path]:
    """(config, run directory) of the run a command works on.

    `run_dir`: a run directory to read `config.toml` from (with `overrides`); giving `toml` as well is refused.
    Otherwise `config`, already resolved by the command line, or, when it is None, the config resolved here from
    `toml` and `overrides`. `connect`: a router endpoint that replaces `bus.connect`."""
    try:
        if run_dir is not None:
            if toml is not None:
                raise RunSetupError(f"--run reads {run_dir}/config.toml; give either --run or --config, not both")
            config = load_run_config(RunConfig, run_dir, overrides)
        else:
            if config is None:
                config = resolve_config(RunConfig, toml, overrides)
            run_dir = config.output_dir()
        if connect:
            config = dataclasses.replace(config, bus=dataclasses.replace(config.bus, connect=(connect,)))
    except ConfigError as err:
        raise RunSetupError(f"config error: {err}") from None
    except ValueError as err:  # a malformed --connect endpoint
        raise RunSetupError(f"--connect: {err}") from None
    return config, run_dir


def open_run_for(command: str, config: RunConfig | None, **where: Any) -> tuple[RunConfig, Path] | None:
    """`open_run(config, **where)` for `impulse COMMAND`: on a problem, its message is printed to stderr as
    `impulse COMMAND: ...` and None is returned (the command then exits with its usage status)."""
    try:
        return open_run(config, **where)
    except RunSetupError as err:
        print(f"impulse {command}: {err}", file=sys.stderr)
        return None


def create_run_dir(run_dir: Path) -> bool:
    """Make `run_dir` (and the folders above it) if it is not there; whether this call made it, which is what
    allows `remove_unstarted_run` to take it back after a refusal."""
    created = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    return created


def remove_unstarted_run(run_dir: Path, checkpoints: Path) -> bool:
    """Remove `run_dir`, made by this command (`create_run_dir`) for a new run that was refused before it trained,
    with all it holds (config.toml, an empty metrics.jsonl); never when `checkpoints`, its checkpoint directory,
    holds a step. Only `run_dir` goes, not the folders made above it. Returns whether it is gone."""
    if holds_checkpoints(checkpoints):
        return False
    shutil.rmtree(run_dir, ignore_errors=True)
    return not run_dir.exists()


def run_dir_of(path: Path) -> Path:
    """The run directory holding config.toml: PATH itself, or up to two levels above a checkpoint folder
    (`checkpoints/<step>`); `FileNotFoundError` when there is none."""
    for candidate in (path, path.parent, path.parent.parent):
        if (candidate / "config.toml").is_file():
            return candidate
    raise FileNotFoundError(f"no config.toml in {path} or above it: give a run directory")


def locate_checkpoint(path: Path) -> tuple[Path, int | None]:
    """(run directory, checkpoint step) of a path given as `--checkpoint`: a run directory (or a shipped agent),
    whose newest checkpoint is meant (step None), or one checkpoint's folder `RUN/checkpoints/<step>`.
    `FileNotFoundError` when no config.toml is found (`run_dir_of`)."""
    run_dir = run_dir_of(path)
    return run_dir, (int(path.name) if path != run_dir and path.name.isdigit() else None)


def fine_tuning_for(command: str, init_from: Path | None, config: RunConfig, *,
                    resume: Path | None = None) -> tuple[Path | None, RunConfig] | None:
    """`impulse COMMAND --init-from PATH` (train, launch, learner): the source's run directory (`run_dir_of`) and
    `config` with the source's [network] section, whatever the command line said, since the new run starts from
    its parameters; `(None, config)` when no source is given. On a problem (no readable config.toml there, or
    `--resume` as well: a new run against a continued one) its message is printed to stderr as
    `impulse COMMAND: ...` and None is returned (the command then exits with its usage status)."""
    if init_from is None:
        return None, config
    if resume is not None:
        print(f"impulse {command}: --init-from starts a new run and --resume continues one: give one of them",
              file=sys.stderr)
        return None
    try:
        source = run_dir_of(init_from)
        return source, dataclasses.replace(config, network=load_run_config(RunConfig, source).network)
    except (FileNotFoundError, ConfigError) as err:
        print(f"impulse {command}: --init-from: {err}", file=sys.stderr)
        return None
