"""The table of `impulse` subcommands: for each, what it does, the config it resolves, its own options, the function
that runs it and the role its process holds on a secured router.

Kept apart from argument parsing (`deploy.cli`) so that adding a command means adding one row. The table names the
function that runs a command by its module and name (`runs="train:run_train"`) and imports that module only when
the command runs (`Command.run_function`): the parser needs only the options (`deploy.commands.options`), so
`impulse --help` and a config error answer at once while a command module imports what it needs at its top.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

from impulse.bus.keys import EVALUATOR, RECORDER
from impulse.bus.roles import (
    ACTOR_ROLE,
    CURRICULUM_ROLE,
    FOLLOWS_WEIGHTS,
    LEARNER_BROADCASTS,
    LEARNER_ROLE,
    OPERATOR_ROLE,
    Role,
)
from impulse.bus.routes import patterns
from impulse.deploy.commands import options
from impulse.deploy.run_config import RunConfig

RunFn = Callable[[argparse.Namespace, Any], int | None]

EVALUATOR_ROLE = Role(EVALUATOR, asks=FOLLOWS_WEIGHTS, hears=LEARNER_BROADCASTS)
"""What the evaluator may do on a router with access control: follow the learner's weights (its evaluations go
under its own prefix, which the learner hears)."""
RECORDER_ROLE = Role(RECORDER, hears=(*patterns("traj", "levels_played"), *LEARNER_BROADCASTS))
"""What the recorder may do on a router with access control: hear the actors' trajectories and the levels they
play, and follow the learner (its presence)."""


@dataclass(frozen=True)
class Command:
    """One `impulse` subcommand."""

    name: str
    summary: str
    """One line for `impulse --help`."""
    description: str
    """What the command does, for `impulse NAME --help`."""
    runs: str
    """The function that runs it, as "MODULE:FUNCTION" of a module in this package; called with the parsed
    arguments and the resolved config (None without one), it returns the exit status."""
    config: type | None = None
    """The config dataclass it resolves from --config and key=value overrides; None if it takes none."""
    arguments: Callable[[argparse.ArgumentParser], None] | None = None
    """Adds the command's own options (beyond --config, --print-config and key=value overrides)."""
    role: Role | None = None
    """The role of the process the command runs, for a router's access control (`run_roles`); None for tools,
    which are operators."""

    def run_function(self) -> RunFn:
        """The function named by `runs`, importing its module (and what that imports: JAX for most) now."""
        module, _, function = self.runs.partition(":")
        return cast(RunFn, getattr(importlib.import_module(f"{__name__}.{module}"), function))


COMMANDS: tuple[Command, ...] = (
    Command(
        "train",
        "train a policy in one process: fused rollout, PPO and curriculum",
        "Fused single-process training: rollouts, PPO updates and the curriculum in one jitted loop on one "
        "device. Writes checkpoints and the resolved config.toml to the run directory.",
        config=RunConfig,
        runs="train:run_train",
        arguments=options.add_train_arguments,
    ),
    Command(
        "train-bc",
        "clone a policy from a recorded dataset (behaviour cloning)",
        "Behaviour cloning: the policy learns to take the actions of a dataset the recorder wrote (--dataset PATH), "
        "by maximum likelihood, from the episodes [bc] selects (solved only by default). The environment is the "
        "dataset's; the network the one that recorded it unless named. Writes a run directory (checkpoint, "
        "metrics.jsonl, eval.json) that `impulse eval` and `impulse train --init-from` read.",
        config=RunConfig,
        runs="train_bc:run_train_bc",
        arguments=options.add_train_bc_arguments,
    ),
    Command(
        "launch",
        "run learner, curriculum and actors as local processes",
        "Local multi-process run: one learner, actors.num_actors actors and, when env.levels is random, the "
        "curriculum service (and, with --view, the Rerun viewer; with --record alone, a Rerun server that records) "
        "as separate processes talking over Zenoh, with a "
        "live status display. A "
        "crashed process is restarted with a back-off (the learner with --resume); Ctrl-C stops everything in "
        "order, the learner writing a final checkpoint. Logs go to RUN_DIR/logs/.",
        config=RunConfig,
        runs="launch:run_launch",
        arguments=options.add_launch_arguments,
    ),
    Command(
        "learner",
        "run the learner process alone (multi-host)",
        "The learner service: receives trajectories, applies corrected PPO updates, publishes weights, "
        "checkpoints.",
        config=RunConfig,
        runs="services:run_learner",
        arguments=options.add_learner_arguments,
        role=LEARNER_ROLE,
    ),
    Command(
        "actor",
        "run one actor process alone (multi-host)",
        "An actor service: runs batched rollouts with the newest weights and publishes trajectories and level "
        "results.",
        config=RunConfig,
        runs="services:run_actor",
        arguments=options.add_actor_arguments,
        role=ACTOR_ROLE,
    ),
    Command(
        "evaluator",
        "run the evaluator process alone (multi-host)",
        "The evaluator: follows the learner's weights and scores the newest policy every evaluator.every_updates "
        "versions on the level sets evaluator.levels names (e.g. kinetix:s,handmade), 20 attempts per level as "
        "Kinetix scores; the learner writes the scores to metrics.jsonl. `impulse launch` starts it when "
        "evaluator.levels is set.",
        config=RunConfig,
        runs="evaluator:run_evaluator",
        arguments=options.add_evaluator_arguments,
        role=EVALUATOR_ROLE,
    ),
    Command(
        "recorder",
        "run the recorder process alone (multi-host)",
        "The recorder: hears the actors' trajectories and the levels they play, and writes whole episodes to a "
        "zarr dataset (recorder.path or --out; shards written whole, so a kill loses no finished shard; "
        "recorder.max_gigabytes bounds it). `impulse launch` starts it when recorder.path is set; "
        "`impulse train-bc --dataset PATH` learns from it.",
        config=RunConfig,
        runs="recorder:run_recorder",
        arguments=options.add_recorder_arguments,
        role=RECORDER_ROLE,
    ),
    Command(
        "curriculum",
        "run the curriculum service alone (multi-host)",
        "The curriculum service and its live controls. `serve` runs the service (it keeps the level buffer, "
        "scores actors' level results, serves level batches and checkpoints itself; `impulse launch` starts it "
        "when env.levels is random). `set KEY=VALUE ... --run RUN_DIR` changes live knobs (replay_prob, "
        "temperature, staleness_coef, score, num_edits, sfl_ratio, ...), applied at the next sample; `get` "
        "prints them; `inspect` prints the buffer (histograms, top levels, lineage; --json, --render DIR).",
        runs="curriculum:run",
        arguments=options.add_curriculum_arguments,
        role=CURRICULUM_ROLE,
    ),
    Command(
        "router",
        "run a Zenoh router for a multi-host run",
        "A Zenoh router for a multi-host run: learner, curriculum and actors on any machine connect to it "
        "(--connect ENDPOINT). Its [router] config section sets where it listens, the routers of other hosts it "
        "links to, and TLS, passwords and access control from a credentials directory (docs/multi-host.md).",
        config=RunConfig,
        runs="router:run_router_command",
        arguments=options.add_router_arguments,
    ),
    Command(
        "eval",
        "evaluate a checkpoint on the hand-made levels",
        "Evaluate a checkpoint: solve rate, mean return and episode length per level over K episodes each, as "
        "a table (and JSON with --json). Uses the config saved in the run directory.",
        config=RunConfig,
        runs="train:run_eval",
        arguments=options.add_eval_arguments,
    ),
    Command(
        "export",
        "write a run's policy alone into a small directory, to share or ship",
        "Copy the policy (network parameters and optimiser state) of a run's checkpoint into a new run directory "
        "with its config.toml and agent.json (source, update, env steps, your --note facts), without the "
        "environment and curriculum state: what pretrained/ ships. `impulse eval --checkpoint DIR`, `impulse train "
        "--init-from DIR` and `--resume DIR` read it.",
        config=RunConfig,
        runs="train:run_export",
        arguments=options.add_export_arguments,
    ),
    Command(
        "import-kinetix",
        "import a policy trained with Kinetix as a run directory",
        "Read a Kinetix 3.0.x checkpoint (full_model.pbz2, params.pbz2 or model.pbz2 from its training scripts, or a "
        "pretrained directory with params.safetensors and config.json), map its network exactly onto Impulse's "
        "(entity transformer, permutation-invariant MLP, flat MLP or the impala_fast pixel CNN; anything that "
        "cannot be reproduced exactly is refused with the reason) and write RUN_DIR with config.toml and a "
        "checkpoint that `impulse eval --checkpoint RUN_DIR` evaluates. Settings a .pbz2 does not record take "
        "Kinetix's defaults unless given with --kinetix-config or --kinetix-option; the ones used are printed and "
        "kept in kinetix_import.json.",
        config=RunConfig,
        runs="import_kinetix:run_import",
        arguments=options.add_import_arguments,
    ),
    Command(
        "levels",
        "inspect, validate, convert and render level files",
        "Level file tools for Kinetix JSON files (also Impulse's own level format): `validate FILE...` prints "
        "every problem, `show FILE` describes a level, `render FILE -o OUT.png` draws it (`render PATH... --video "
        "OUT.mp4` plays levels with no-op actions into a video), `convert IN OUT --size s|m|l` re-sizes and "
        "normalises it.",
        runs="levels:run",
        arguments=options.add_levels_arguments,
    ),
    Command(
        "compare",
        "compare training runs of either mode: progress, metrics, config differences",
        "Compare run directories of `impulse train` and `impulse launch` (running ones too): one table row per "
        "run with its mode, progress, wall clock and the final and best value of each --metric (default: "
        "solve_rate, and eval/mean when a run has it), with --threshold the env steps and time to reach it, then "
        "the config keys whose values differ. --plot FILE.png draws the curves against --by, --json prints JSON.",
        runs="compare:run",
        arguments=options.add_compare_arguments,
    ),
    Command(
        "studio",
        "open Impulse Studio in the browser: browse, edit and play levels, watch an agent",
        "A local web app (docs/studio.md): a gallery of level sets (hand-made, Kinetix's, saved, --levels) drawn as "
        "thumbnails; an editor that adds, moves, deletes and re-roles shapes and saves Kinetix JSON files that "
        "`impulse levels validate` accepts; play on the server's engine with the keyboard, and watch an agent "
        "(--run, or pretrained/*) play. Listens on 127.0.0.1; any other --host needs --token.",
        runs="studio:run",
        arguments=options.add_studio_arguments,
    ),
    Command(
        "tensorboard",
        "write TensorBoard event files for runs from their metrics.jsonl",
        "Write RUN_DIR/tensorboard/ from RUN_DIR/metrics.jsonl, the scalars a run writes live when "
        "monitor.tensorboard is on (one per numeric column, step env_steps), for runs that have none. A folder that "
        "already holds event files is refused unless --replace. View with `tensorboard --logdir runs/`.",
        runs="tensorboard:run",
        arguments=options.add_tensorboard_arguments,
    ),
    Command(
        "config",
        "describe the configuration keys",
        "The configuration reference: `describe [KEY]` prints every key (or one key, or a section's keys) with "
        "its type, default and meaning, from the config dataclasses themselves (docs/config.md holds the same).",
        runs="config:run",
        arguments=options.add_config_arguments,
    ),
    Command(
        "view",
        "open the Rerun viewer on a run",
        "The Rerun viewer for a run, live: starts the server the run's processes stream to (monitor.url) and "
        "the native viewer when there is a display, else the web viewer, whose address it prints. --record "
        "FILE.rrd also writes everything streamed to a file (open it later with `rerun FILE.rrd`); --headless "
        "--record FILE.rrd records with no viewer. `impulse launch --view` (or `--record` alone) starts it for you.",
        config=RunConfig,
        runs="view:run_view",
        arguments=options.add_view_arguments,
    ),
)


def run_roles() -> tuple[Role, ...]:
    """Every role a run's processes may play: those of the commands that run a process, and the operator (the
    launcher, command-line tools and watchers). What `impulse router` enforces and `--roles` lists."""
    return (*(command.role for command in COMMANDS if command.role is not None), OPERATOR_ROLE)
