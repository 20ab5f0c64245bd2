"""`impulse recorder`: the recorder process alone (`learner.recorder`), against a running run on this machine or
across machines (`--connect ENDPOINT`, with the recorder's own credentials); `impulse launch` starts it with the run
when `recorder.path` is set. Give the run's config (`--config` and the same overrides as the run, or `--run
RUN_DIR` where the run directory is visible) and where to write (`recorder.path=...` or `--out PATH`)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from impulse.actors.wire import trajectory_template
from impulse.bus.session import Bus
from impulse.deploy.commands import RECORDER_ROLE
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.run_dirs import open_run_for
from impulse.deploy.runtime.runloop import LoopOptions, run_loop
from impulse.engine.env.spec import env_from_config
from impulse.learner.dataset import DatasetError, DatasetWriter
from impulse.learner.recorder import RECORDER_ID, RecorderService

log = logging.getLogger("impulse.service")


def dataset_path(config: RunConfig, run_dir: Path) -> Path | None:
    """Where the run's recorder writes: `recorder.path` with "{run_dir}" filled in; None when it is empty."""
    if not config.recorder.path:
        return None
    return Path(config.recorder.path.replace("{run_dir}", str(run_dir)))


def run_recorder(args: argparse.Namespace, config: RunConfig) -> int:
    opened = open_run_for("recorder", config, run_dir=args.run, toml=getattr(args, "config", None),
                          overrides=args.overrides, connect=args.connect)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened
    path = args.out or dataset_path(config, run_dir)
    if path is None:
        print("impulse recorder: where should it write? set recorder.path=PATH (or pass --out PATH)",
              file=sys.stderr)
        return EXIT_USAGE

    spec, _ = env_from_config(config.env)
    template = trajectory_template(spec, config.ppo.num_envs, config.ppo.num_steps)
    try:
        writer = DatasetWriter(path, config.env, config.network, max_bytes=int(config.recorder.max_gigabytes * 1e9),
                               when_full=config.recorder.when_full)
    except (DatasetError, OSError) as err:
        print(f"impulse recorder: {err}", file=sys.stderr)
        return EXIT_FAILED
    with Bus(config.bus, config.name, RECORDER_ROLE.name, RECORDER_ID) as bus:
        service = RecorderService(config.recorder, bus=bus, writer=writer, template=template, sizes=spec.sizes,
                                  wire_compact=config.bus.wire_compact,
                                  status_every_s=config.bus.status_every_s)
        log.info("recorder up: run %s, writing whole episodes to %s (%d shards there already, %.1f MB of %.1f GB)",
                 config.name, path, writer.next_shard, writer.bytes_used / 1e6, writer.max_bytes / 1e9)
        run_loop(service, LoopOptions())
    counts = writer.counts
    log.info("recorder done: %d episodes (%d steps) in %d shards this time; %d episodes cut, %d without their level",
             counts["episodes_written"], counts["steps_written"], counts["shards_written"],
             service.assembler.counts["episodes_cut"], service.counts["episodes_without_level"])
    return 0
