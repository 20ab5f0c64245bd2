"""`impulse import-kinetix`: turn a Kinetix checkpoint into an Impulse run directory that `impulse eval` (and the
rest of Impulse) reads like one of its own.

The run directory gets config.toml (the resolved config with the network and env settings the policy needs),
a `train` checkpoint item at step 0 (the imported parameters, a fresh optimiser state, policy version 0) and
kinetix_import.json (where it came from and every Kinetix setting the mapping relied on, marking those taken
from Kinetix's defaults because the checkpoint does not record them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp

from impulse.deploy.config import config_to_toml, write_resolved_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.learner.agent import env_and_agent
from impulse.learner.checkpoint import TRAIN, Checkpointer
from impulse.learner.kinetix_import import (
    KinetixImportError,
    check_against,
    describe_settings,
    import_kinetix,
    parse_option,
    read_kinetix_checkpoint,
    with_network,
)
from impulse.learner.update import TrainState, make_optimizer

if TYPE_CHECKING:
    from impulse.learner.kinetix_import import ImportedPolicy

RECORD_FILENAME = "kinetix_import.json"


def run_import(args: argparse.Namespace, config: RunConfig) -> int:
    try:
        options = dict(parse_option(text) for text in args.kinetix_option)
        checkpoint = read_kinetix_checkpoint(args.checkpoint, args.kinetix_config)
        imported = import_kinetix(checkpoint, options)
    except (KinetixImportError, OSError) as err:
        print(f"impulse import-kinetix: {err}", file=sys.stderr)
        return EXIT_USAGE
    env = with_network(config.env, imported)
    if env.size != config.env.size:
        print(f"env.size set to {env.size!r}: the flat network reads that size's observation", file=sys.stderr)
    config = dataclasses.replace(config, env=env, network=imported.network, run_dir=str(args.out))
    try:
        count = write_checkpoint(config, imported, args.out)
    except (KinetixImportError, RuntimeError, ValueError) as err:
        print(f"impulse import-kinetix: {err}", file=sys.stderr)
        return EXIT_FAILED
    record = {"source": checkpoint.source, "kinetix_settings": imported.settings,
              "unread_pickle_classes": sorted(checkpoint.unread_classes)}
    (args.out / RECORD_FILENAME).write_text(json.dumps(record, indent=2, default=str))
    print(f"imported {checkpoint.source}: network {imported.network.kind}, {count:,} parameters, "
          f"env.observation={imported.observation}, env.action={imported.action}, env.size={config.env.size}")
    print("Kinetix settings used (check those from Kinetix's defaults against your run's config):")
    print(describe_settings(imported))
    print(f"wrote {args.out}; evaluate it with: impulse eval --checkpoint {args.out}")
    return 0


def write_checkpoint(config: RunConfig, imported: ImportedPolicy, run_dir: Path) -> int:
    """Write config.toml and the `train` item at step 0 into `run_dir`; returns the parameter count. The tree is
    checked against the network's own before anything is written."""

    run_dir.mkdir(parents=True, exist_ok=True)
    with Checkpointer(run_dir / config.checkpoint.directory, config.checkpoint) as checkpoints:
        if checkpoints.latest_step() is not None:
            raise RuntimeError(f"{run_dir} already holds checkpoints; choose another --out")
        agent = env_and_agent(config.env, config.network).agent
        check_against(imported, jax.eval_shape(agent.init, jax.random.PRNGKey(0)))
        params = jax.tree.map(jnp.asarray, imported.params)
        # The optimiser state's structure does not depend on the schedule's length, so one update will do.
        state = TrainState(params, make_optimizer(config.ppo, 1).init(params), jnp.zeros((), jnp.int32))
        write_resolved_config(config, run_dir)
        checkpoints.save(0, {TRAIN: state}, {"update": 0, "env_steps": 0, "imported_from": "kinetix"},
                         config_to_toml(config))
    return sum(int(x.size) for x in jax.tree.leaves(params))
