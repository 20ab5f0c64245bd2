"""`impulse config describe [KEY]`: the configuration reference in a terminal (deploy.config_reference), one key, a
section (`ppo`) or everything. Exit status 2 for a key that does not exist, with the nearest names."""

from __future__ import annotations

import argparse
import difflib
import shutil
import sys

from impulse.deploy.config_reference import as_text, keys, matching
from impulse.deploy.runtime.exit_codes import EXIT_USAGE

MAX_SHOWN_KEY = 100
"""How much of a long KEY that matches nothing the error message quotes (it is one line)."""


def run(args: argparse.Namespace, _config: object = None) -> int:
    if args.config_action != "describe":
        print("impulse config: give an action: describe [KEY]", file=sys.stderr)
        return EXIT_USAGE

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
