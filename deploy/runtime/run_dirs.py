"""Which run a command works on: its configuration and its run directory, found one way for every command.

A command is given either a run directory (`--run RUN_DIR` for the services and the curriculum tools, `--resume
RUN_DIR` for `impulse train` and `impulse launch`), whose `config.toml` is read with the command line's
`key=value` overrides on top, or a configuration resolved from `--config FILE` and the overrides, whose `run_dir`
is the run directory. `--connect ENDPOINT` replaces `bus.connect` either way.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from impulse.deploy.config import ConfigError, load_run_config, resolve_config
from impulse.deploy.run_config import RunConfig


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
