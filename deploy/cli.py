"""The `impulse` command: parse arguments, set up logging, resolve the command's config, dispatch.

Options shared by every command (`--log-format`, `--log-level`) are accepted before or after the command name.
Config overrides are trailing `key=value` words and may be mixed with options. Errors a user can fix (a bad
config key, an unknown benchmark) end in one line on stderr and exit status 2, never a traceback. Imports are
kept light (no JAX here) so that `--help` and `--print-config` answer at once: the parser is built from the command
table and `deploy.commands.options`, and a command's own module is imported only to run it.

Whatever is typed is input, not code: reading it (the arguments, the config file, the overrides) never ends in a
traceback. A path option that names a directory to read (`--resume`, `--run`, `--init-from`, `--checkpoint`) is
refused at parsing when it names something else (`directory_argument`); a config file or override that cannot be
read is a `ConfigError` (deploy.config); and an unexpected exception while reading them is still one line and
exit status 2 (its traceback is logged at `--log-level debug`). Once a command runs, its exceptions are its own
and propagate as they are, so real bugs stay visible. Output cut short by the reader (`impulse ... | head`) ends
quietly with status 141, as a program killed by SIGPIPE reports in a shell (`main`).
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import select
import stat
import sys
import textwrap
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from impulse.deploy.commands import COMMANDS, Command, bench
from impulse.deploy.config import ConfigError, config_to_toml, resolve_config
from impulse.deploy.runtime.exit_codes import EXIT_BROKEN_PIPE, EXIT_USAGE
from impulse.deploy.runtime.log_setup import LEVELS, configure_logging

DIRECTORY_OPTIONS = frozenset({"--resume", "--run", "--init-from", "--checkpoint"})
"""Options whose `type=Path` value names a directory a command reads (a run directory or a checkpoint folder);
every parser of the CLI checks their kind with `directory_argument`."""

MAX_MESSAGE_CHARS = 2000
"""An error message is clipped to this many characters: it is one line, however long the input it quotes."""

log = logging.getLogger("impulse.cli")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `impulse` console script; returns the process exit status.

    A `BrokenPipeError` from writing to stdout after its reader closed it (`impulse config describe | head`) ends
    the command quietly with status 141 (`EXIT_BROKEN_PIPE`, what a shell shows for a program SIGPIPE stopped),
    without a traceback, for every command. As Python's documentation advises, stdout is then pointed at
    /dev/null (`os.dup2`), so that flushing it at exit raises nothing either. A broken pipe anywhere else (a socket,
    a child process's stdin) is a real error and propagates.
    """
    try:
        status = _main(argv)
        sys.stdout.flush()  # inside the try: output still buffered can meet a closed pipe here too
        return status
    except BrokenPipeError:
        if not _stdout_closed():
            raise
        _discard_stdout()
        return EXIT_BROKEN_PIPE


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
    except BrokenPipeError:
        raise  # help or usage written to a closed stdout: `main` ends quietly
    except Exception as err:  # noqa: BLE001 - input must never end in a traceback; argparse's own errors exit 2
        _input_error("impulse", "cannot parse the command line", err)
        return EXIT_USAGE
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


def directory_argument(text: str) -> Path:
    """The argparse `type` of the options that name a directory to read (`DIRECTORY_OPTIONS`): `text` as a Path,
    or `argparse.ArgumentTypeError` (exit status 2, one message) when it is empty, holds a NUL character, names a
    file, a device or a FIFO, or cannot be looked at (too long, no permission). A path that does not exist is let
    through: the command says what it looked for there (a run directory's config.toml)."""
    shown = _one_line(text, 200)
    if not text:
        raise argparse.ArgumentTypeError("an empty path: give a directory")
    if "\x00" in text:
        raise argparse.ArgumentTypeError(f"{shown}: a path cannot hold a NUL character")
    try:
        info = os.stat(text)
    except FileNotFoundError:
        return Path(text)
    except NotADirectoryError:
        raise argparse.ArgumentTypeError(f"{shown}: not a directory (a part of the path is a file)") from None
    except OSError as err:
        raise argparse.ArgumentTypeError(f"{shown}: {err.strerror or err}") from None
    if not stat.S_ISDIR(info.st_mode):
        raise argparse.ArgumentTypeError(f"{shown}: not a directory (a run directory or a checkpoint folder is "
                                         "expected)")
    return Path(text)


class _Parser(argparse.ArgumentParser):
    """The CLI's argument parser: an option of `DIRECTORY_OPTIONS` declared with `type=Path`, by any command module,
    is checked with `directory_argument` instead, so that each command need not repeat the check. Sub-parsers (a
    command's own actions too) are of this class, since argparse makes them of their parent's class."""

    def add_argument(self, *names: str, **kwargs: Any) -> argparse.Action:
        if kwargs.get("type") is Path and DIRECTORY_OPTIONS.intersection(names):
            kwargs["type"] = directory_argument
        return super().add_argument(*names, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
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
            text = config_to_toml(config) if args.print_config else ""
        except ConfigError as e:
            print(f"impulse {spec.name}: config error: {_one_line(str(e))}", file=sys.stderr)
            return EXIT_USAGE
        except Exception as err:  # noqa: BLE001 - reading input must not end in a traceback (logged at debug)
            _input_error(f"impulse {spec.name}", "config error: cannot read the configuration", err)
            return EXIT_USAGE
        if args.print_config:
            sys.stdout.write(text)
            return 0
    return int(spec.run_function()(args, config) or 0)


def _run_bench(args: argparse.Namespace) -> int:
    try:
        return bench.run(args.name, args.args)
    except bench.UnknownBenchmark as e:
        print(f"impulse bench: {e}", file=sys.stderr)
        return EXIT_USAGE


def _input_error(who: str, what: str, err: Exception) -> None:
    """Report an unexpected exception met while reading the command line or the config as one line on stderr; its
    traceback goes to the log at debug level, so that a bug in the reading code can still be found."""
    log.debug("%s", what, exc_info=err)
    print(f"{who}: {what}: {type(err).__name__}: {_one_line(str(err))}", file=sys.stderr)


def _one_line(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """`text` on one line (unprintable characters, newlines among them, written as escapes), clipped to `limit`."""
    if not text.isprintable():
        text = "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in text)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"


def _stdout_closed() -> bool:
    """Whether stdout is a pipe or socket whose reader has gone: what a BrokenPipeError from stdout means, told
    apart from one raised by another pipe. Without poll(2), a broken pipe is taken to be stdout's."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return False  # no file descriptor (replaced, or captured in a test): the error is not stdout's
    if not hasattr(select, "poll"):
        return True
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))


def _discard_stdout() -> None:
    """Point stdout's file descriptor at /dev/null, so that what is still buffered is flushed at exit without
    another BrokenPipeError (Python's documentation, "Note on SIGPIPE")."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)


def _is_override(word: str) -> bool:
    return "=" in word and not word.startswith("-")


@functools.cache
def _version() -> str:
    """The installed package's version, looked up once: every parser built (one per `main` call) shows it."""
    try:
        return metadata.version("impulse")
    except metadata.PackageNotFoundError:
        return "unknown (not installed; run `pip install -e .`)"


if __name__ == "__main__":
    sys.exit(main())
