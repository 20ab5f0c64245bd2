"""Command-line options several commands share, declared once: which run a process joins (`--run`) and which
router it connects to (`--connect`)."""

from __future__ import annotations

import argparse
from pathlib import Path

SERVICE_RUN_HELP = ("use the config saved in RUN_DIR (as `impulse launch` writes it); key=value overrides still "
                    "apply")
"""`--run` for a service process, which may also be started from a TOML file and overrides instead."""
TOOL_RUN_HELP = "the run's directory"
"""`--run` for a tool that talks to a running run (it needs the run's config)."""


def add_run_option(parser: argparse.ArgumentParser, help: str = SERVICE_RUN_HELP, required: bool = False) -> None:
    """`--run RUN_DIR`: the run directory whose config.toml the command reads (`deploy.runtime.run_dirs`)."""
    parser.add_argument("--run", type=Path, metavar="RUN_DIR", required=required, help=help)


def add_connect_option(parser: argparse.ArgumentParser) -> None:
    """`--connect ENDPOINT`: the zenoh endpoint (a router) to connect to instead of the run's `bus.hub`."""
    parser.add_argument("--connect", metavar="ENDPOINT",
                        help="zenoh endpoint to connect to instead of the run's bus.hub, e.g. "
                        "tls/hostA.example.org:7447")


def add_run_and_connect(parser: argparse.ArgumentParser, help: str = SERVICE_RUN_HELP,
                        required: bool = False) -> None:
    """Both: what every process that joins a run's bus takes."""
    add_run_option(parser, help, required)
    add_connect_option(parser)
