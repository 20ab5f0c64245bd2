"""The `impulse` command: parse arguments, set up logging, resolve the command's config, dispatch.

Options shared by every command (`--log-format`, `--log-level`) are accepted before or after the command name.
Config overrides are trailing `key=value` words and may be mixed with options. Errors a user can fix (a bad
config key, an unknown benchmark) end in one line on stderr and exit status 2, never a traceback. Imports are
kept light (no JAX here) so that `--help` and `--print-config` answer at once.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path

from impulse.deploy.commands import COMMANDS, Command, bench
from impulse.deploy.config import ConfigError, config_to_toml, resolve_config
from impulse.deploy.runtime.log_setup import LEVELS, configure_logging

EXIT_USAGE = 2


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `impulse` console script; returns the process exit status."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        if args.spec is not None and args.spec.config is not None and all(_is_override(x) for x in extra):
            args.overrides += extra
        else:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
    configure_logging(args.log_format, args.log_level)
    try:
        if args.command == "bench":
            return _run_bench(args)
        return _run_command(args.spec, args)
    except KeyboardInterrupt:
        print(f"impulse {args.command}: interrupted", file=sys.stderr)
        return 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="impulse",
        description="Impulse: Kinetix-compatible 2D physics RL in JAX, fused or distributed.",
        allow_abbrev=False,
    )
    parser.add_argument("--version", action="version", version=f"impulse {_version()}")
    _add_logging_options(parser, with_defaults=True)
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for spec in COMMANDS:
        _add_command(commands, spec)
    _add_bench(commands)
    return parser


def _add_command(commands: argparse._SubParsersAction, spec: Command) -> None:
    description = textwrap.fill(spec.description, 79)
    p = commands.add_parser(
        spec.name, help=spec.summary, description=description, allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_logging_options(p, with_defaults=False)
    if spec.arguments is not None:
        spec.arguments(p)
    if spec.config is not None:
        p.add_argument("--config", type=Path, metavar="FILE.toml", help="TOML file with config values")
        p.add_argument(
            "--print-config", action="store_true",
            help="print the resolved config (defaults, file, overrides) as TOML and exit",
        )
        p.add_argument(
            "overrides", nargs="*", metavar="key=value",
            help="config overrides with dotted keys, e.g. ppo.learning_rate=3e-4 env.size=m",
        )
    p.set_defaults(spec=spec)


def _add_bench(commands: argparse._SubParsersAction) -> None:
    try:
        names = ", ".join(bench.available()) or "(none)"
    except ImportError:
        names = "(the benchmarks package is not importable)"
    p = commands.add_parser(
        "bench", help="run a benchmark (prints JSON lines)", allow_abbrev=False,
        description="Run the benchmark module benchmarks.NAME; arguments after NAME are passed to it "
        "(see `impulse bench NAME --help`).",
        epilog=f"available benchmarks: {names}",
    )
    _add_logging_options(p, with_defaults=False)
    p.add_argument("name", metavar="NAME", help="benchmark module name")
    p.add_argument("args", nargs=argparse.REMAINDER, metavar="ARGS", help="arguments for the benchmark")
    p.set_defaults(spec=None)


def _add_logging_options(parser: argparse.ArgumentParser, with_defaults: bool) -> None:
    # Subcommands suppress their defaults so they never overwrite a value given before the command name.
    default_format = "text" if with_defaults else argparse.SUPPRESS
    default_level = "info" if with_defaults else argparse.SUPPRESS
    parser.add_argument(
        "--log-format", choices=("text", "json"), default=default_format,
        help="text for terminals, json for one object per line (default: text)",
    )
    parser.add_argument(
        "--log-level", type=str.lower, choices=LEVELS, default=default_level, help="default: info",
    )


def _run_command(spec: Command, args: argparse.Namespace) -> int:
    config = None
    if spec.config is not None:
        try:
            config = resolve_config(spec.config, args.config, args.overrides)
        except ConfigError as e:
            print(f"impulse {spec.name}: config error: {e}", file=sys.stderr)
            return EXIT_USAGE
        if args.print_config:
            sys.stdout.write(config_to_toml(config))
            return 0
    return int(spec.run(args, config) or 0)


def _run_bench(args: argparse.Namespace) -> int:
    try:
        return bench.run(args.name, args.args)
    except bench.UnknownBenchmark as e:
        print(f"impulse bench: {e}", file=sys.stderr)
        return EXIT_USAGE


def _is_override(word: str) -> bool:
    return "=" in word and not word.startswith("-")


def _version() -> str:
    try:
        return metadata.version("impulse")
    except metadata.PackageNotFoundError:
        return "unknown (not installed; run `pip install -e .`)"


if __name__ == "__main__":
    sys.exit(main())
