"""`impulse config describe [KEY]`: the configuration reference in a terminal (deploy.config_reference), one key, a
section (`ppo`) or everything. Exit status 2 for a key that does not exist, with the nearest names."""

from __future__ import annotations

import argparse
import difflib
import shutil
import sys

from impulse.deploy.runtime.exit_codes import EXIT_USAGE

MAX_SHOWN_KEY = 100
"""How much of a long KEY that matches nothing the error message quotes (it is one line)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="config_action", metavar="ACTION")
    describe = actions.add_parser(
        "describe", help="every key with its type, default and meaning",
        description="Print configuration keys with their type, default and meaning: KEY alone, every key of a "
        "section (ppo, curriculum, ...), or all of them. docs/config.md holds the same reference.")
    describe.add_argument("key", nargs="?", help="a key (ppo.num_envs) or a section (ppo); all when omitted")


def run(args: argparse.Namespace, _config: object = None) -> int:
    if args.config_action != "describe":
        print("impulse config: give an action: describe [KEY]", file=sys.stderr)
        return EXIT_USAGE
    from impulse.deploy.config_reference import as_text, keys, matching

    selected = matching(args.key)
    if not selected:
        names = [k.name for k in keys()]
        names += sorted({name.split(".")[0] for name in names if "." in name})
        near = difflib.get_close_matches(args.key, names, n=3)
        hint = f"; did you mean {', '.join(near)}?" if near else ""
        shown = args.key if len(args.key) <= MAX_SHOWN_KEY else args.key[:MAX_SHOWN_KEY] + "..."
        print(f"impulse config describe: no key or section {shown!r}{hint}", file=sys.stderr)
        return EXIT_USAGE
    print(as_text(selected, width=max(shutil.get_terminal_size().columns - 4, 40)))
    return 0
