"""`impulse train-bc --dataset PATH`: behaviour cloning of a policy from a recorded dataset (`learner.bc`), into a
new run directory that `impulse eval`, `impulse export` and `impulse train --init-from` read like any other.

The environment (`[env]`) is the dataset's: the observations, actions and size its episodes were recorded with;
`env.*` overrides are refused where they differ from it. The network is the one that recorded the dataset unless
`--config` or `network.*` overrides name another. The selection and the optimiser are the `[bc]` section. After
cloning, the policy is scored as at the end of `impulse train` (`eval.levels`, else the recorded levels) and the
scores written to eval.json; each epoch's losses go to metrics.jsonl."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from impulse.deploy.config import ConfigError, config_from_dict, config_to_toml, write_resolved_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.compile_cache import enable_compile_cache
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.run_dirs import create_run_dir, open_run_for, remove_unstarted_run
from impulse.engine.env.config import EnvConfig
from impulse.learner.agent import env_and_agent
from impulse.learner.bc import (
    EpochStats,
    clone,
    cloning_data,
    is_kinetix_dataset,
    kinetix_cloning_data,
    select_episodes,
)
from impulse.learner.checkpoint import TRAIN, Checkpointer
from impulse.learner.config import NetworkConfig
from impulse.learner.dataset import DatasetError, open_dataset
from impulse.learner.run import final_evaluation
from impulse.learner.run_directory import existing_run, holds_checkpoints
from impulse.learner.update import TrainState, make_optimizer

log = logging.getLogger("impulse.train")


def _with_dataset_sections(config: RunConfig, env: dict, network: dict, source: str) -> RunConfig:
    """`config` with the dataset's env section, and its network section unless the config names another."""
    recorded = config_from_dict(EnvConfig, env, source)
    given = dataclasses.asdict(config.env)
    differ = {key: value for key, value in given.items() if value != getattr(EnvConfig(), key)
              and value != getattr(recorded, key)}
    if differ:
        raise ConfigError(f"env is the dataset's ({source}); these settings differ from it: "
                          + ", ".join(f"env.{key}={value!r} (recorded: {getattr(recorded, key)!r})"
                                      for key, value in differ.items()))
    if config.network == NetworkConfig() and network:
        config = dataclasses.replace(config, network=config_from_dict(NetworkConfig, network, source))
    return dataclasses.replace(config, env=recorded)


def run_train_bc(args: argparse.Namespace, config: RunConfig) -> int:
    dataset = None
    try:
        if is_kinetix_dataset(args.dataset):
            log.info("%s is a dataset in Kinetix's offline format: env and network as configured (it records "
                     "neither); every transition its mask marks is learnt from", args.dataset)
        else:
            dataset = open_dataset(args.dataset)
            config = _with_dataset_sections(config, dataset.env, dataset.network, f"{args.dataset}'s attributes")
    except (DatasetError, ConfigError, ValueError) as err:
        print(f"impulse train-bc: {err}", file=sys.stderr)
        return EXIT_USAGE
    opened = open_run_for("train-bc", config)
    if opened is None:
        return EXIT_USAGE
    config, run_dir = opened
    if holds_checkpoints(run_dir / config.checkpoint.directory):
        print(f"impulse train-bc: {existing_run(run_dir)}", file=sys.stderr)
        return EXIT_FAILED
    enable_compile_cache()
    created = create_run_dir(run_dir)
    write_resolved_config(config, run_dir)
    try:
        clone_into(config, args.dataset, dataset, run_dir)
    except (DatasetError, ValueError) as err:  # the Kinetix reader's LevelFileError is a ValueError
        print(f"impulse train-bc: {err}", file=sys.stderr)
        if created and remove_unstarted_run(run_dir, run_dir / config.checkpoint.directory):
            print(f"impulse train-bc: removed {run_dir}, created for this run: nothing was trained", file=sys.stderr)
        return EXIT_FAILED
    return 0


def clone_into(config: RunConfig, path: Path, dataset: Any, run_dir: Path) -> None:
    """Clone a policy from the dataset at `path` (`dataset`: ours opened, None for one in Kinetix's format) per
    `config` and write it, its metrics and its scores into `run_dir`."""

    spec, env_params, agent = env_and_agent(config.env, config.network)
    if dataset is None:
        train, held_out = kinetix_cloning_data(path, agent, config.bc.validation_fraction, config.seed)
        log.info("Kinetix dataset %s: learning from %d transitions, %d held out", path, train.steps, held_out.steps)
    else:
        index = dataset.index()
        train_rows, held_rows = select_episodes(index, config.bc, config.seed)
        log.info("dataset %s: %d episodes (%d steps, %.0f%% solved); learning from %d episodes (%d steps), %d held "
                 "out", path, index.episodes, index.steps, 100 * index.solved.mean() if index.episodes else 0,
                 int(train_rows.sum()), int(index.length[train_rows].sum()), int(held_rows.sum()))
        train, held_out = cloning_data(dataset, train_rows, agent), cloning_data(dataset, held_rows, agent)
    metrics = (run_dir / "metrics.jsonl").open("w")

    def report(stats: EpochStats) -> None:
        log.info("epoch %d/%d: loss %.4f, held-out loss %.4f, held-out agreement %.0f%% (%.1f s)", stats.epoch,
                 config.bc.epochs, stats.loss, stats.held_out_loss, 100 * stats.held_out_agreement, stats.seconds)
        row = {"epoch": stats.epoch, "bc/loss": stats.loss, "bc/held_out_loss": stats.held_out_loss,
               "bc/held_out_agreement": stats.held_out_agreement, "seconds": stats.seconds}
        metrics.write(json.dumps({key: (None if value != value else value) for key, value in row.items()}) + "\n")
        metrics.flush()

    with metrics:
        params = clone(agent, agent.init(jax.random.PRNGKey(config.seed)), train, held_out, config.bc, config.seed,
                       report)
    state = TrainState(params, make_optimizer(config.ppo, 1).init(params), jnp.zeros((), jnp.int32))
    counters = {"update": 0, "env_steps": 0, "cloned_from": str(path), "bc_epochs": config.bc.epochs,
                "bc_steps": train.steps}
    with Checkpointer(run_dir / config.checkpoint.directory, config.checkpoint) as checkpoints:
        checkpoints.save(0, {TRAIN: state}, counters, config_to_toml(config))
    log.info("wrote the cloned policy to %s", run_dir / config.checkpoint.directory)
    final_evaluation(config, agent, env_params, params, run_dir)
