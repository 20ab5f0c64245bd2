"""`impulse tensorboard RUN_DIR...`: TensorBoard event files for runs that have none, from their metrics.jsonl.

Runs write their event files live (`monitor.tensorboard`); this is for runs made before that, with it off, or
copied without their `tensorboard/` folder. It writes what a live run would (`monitor.scalars.export_tensorboard`,
the same `write_scalars`), into `RUN_DIR/tensorboard/`. A run whose folder already holds event files is refused,
since a second copy of each point would be drawn twice, unless `--replace` deletes them first. Exit status 2, with
nothing written, when a directory has no metrics.jsonl or already has event files without `--replace`.
"""

from __future__ import annotations

import argparse
import sys

from impulse.deploy.runtime.exit_codes import EXIT_USAGE
from impulse.monitor.scalars import TENSORBOARD_DIR, event_files, export_tensorboard


def run(args: argparse.Namespace, _config: object = None) -> int:
    for run_dir in args.run_dirs:
        if not (run_dir / "metrics.jsonl").is_file():
            print(f"impulse tensorboard: {run_dir} has no metrics.jsonl", file=sys.stderr)
            return EXIT_USAGE
        if event_files(run_dir / TENSORBOARD_DIR) and not args.replace:
            print(f"impulse tensorboard: {run_dir / TENSORBOARD_DIR} already holds event files; --replace rewrites "
                  "them", file=sys.stderr)
            return EXIT_USAGE
    for run_dir in args.run_dirs:
        log_dir = run_dir / TENSORBOARD_DIR
        for old in event_files(log_dir):
            old.unlink()
        rows = export_tensorboard(run_dir / "metrics.jsonl", log_dir)
        print(f"{log_dir}: {rows} rows")
    return 0
