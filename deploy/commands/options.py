"""Every command's options, declared apart from the code that runs the command.

`impulse --help`, `impulse NAME --help` and `--print-config` build the parser from this module and the command
table alone, and the CLI imports the module that runs a command only once that command is chosen
(`deploy.commands.Command.run_function`), so a command module imports what it needs at its top and the parser stays
light (no JAX, no web stack). Options several commands share are declared once: which run a process joins (`--run`)
and which router it connects to (`--connect`)."""

from __future__ import annotations

import argparse
from pathlib import Path

SERVICE_RUN_HELP = ("use the config saved in RUN_DIR (as `impulse launch` writes it); key=value overrides still "
                    "apply")
"""`--run` for a service process, which may also be started from a TOML file and overrides instead."""
TOOL_RUN_HELP = "the run's directory"
"""`--run` for a tool that talks to a running run (it needs the run's config)."""
SIZE_NAMES = ("s", "m", "l")
"""The level size classes, as `engine.physics.sizes.SIZE_NAMES` lists them (importing the engine would load JAX;
tests/deploy/test_cli.py keeps the two alike)."""
VIDEO_STEPS = 256
"""`impulse levels render --video`'s default number of agent steps: a training episode (env.max_timesteps)."""
STUDIO_PORT = 8765
"""`impulse studio`'s default port."""
STUDIO_HOST = "127.0.0.1"
"""`impulse studio`'s default address: this machine only."""
STUDIO_LEVELS_DIR = Path("studio-levels")
"""The folder `impulse studio` saves levels into by default."""


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


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse train`: resume, stop after N updates, or fine-tune."""
    parser.add_argument(
        "--resume", type=Path, metavar="RUN_DIR",
        help="continue the run in RUN_DIR from its newest checkpoint, with the config saved there "
        "(key=value overrides still apply, e.g. total_env_steps to train longer)",
    )
    parser.add_argument(
        "--updates", type=int, metavar="N",
        help="stop after N more updates (checkpointing), even if total_env_steps is not reached",
    )
    parser.add_argument(
        "--init-from", type=Path, metavar="RUN_DIR",
        help="fine-tune: a new run that starts from the policy of RUN_DIR's newest checkpoint (a run directory or "
        "a shipped agent such as pretrained/general-s), with a fresh optimiser, environments and curriculum; the "
        "[network] section comes from RUN_DIR's config.toml",
    )


def add_train_bc_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse train-bc`: the recorded dataset to clone."""
    parser.add_argument("--dataset", type=Path, required=True, metavar="PATH",
                        help="a dataset written by the recorder (recorder.path of a run, or `impulse recorder "
                        "--out`)")


def add_launch_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse launch`: resume or fine-tune, the status cadence, the Rerun viewer and recording."""
    parser.add_argument("--resume", type=Path, metavar="RUN_DIR",
                        help="continue the run in RUN_DIR from its newest checkpoint, with the config saved there")
    parser.add_argument("--init-from", type=Path, metavar="RUN_DIR",
                        help="fine-tune: a new run whose learner starts from the policy of RUN_DIR's newest "
                        "checkpoint (a run directory or a shipped agent such as pretrained/general-s), with a fresh "
                        "optimiser, actors and curriculum; the [network] section comes from RUN_DIR's config.toml")
    parser.add_argument("--status-every", type=float, default=10.0, metavar="SECONDS",
                        help="when the output is not a terminal, log the status lines this often (default 10)")
    parser.add_argument("--view", action="store_true",
                        help="stream to a Rerun viewer: starts `impulse view` (native with a display, else the web "
                        "viewer, whose address is logged) and turns monitoring on in every process")
    parser.add_argument("--record", type=Path, metavar="FILE.rrd",
                        help="write everything the processes stream to FILE.rrd (open it later with `rerun "
                        "FILE.rrd`); turns monitoring on like --view, and without --view starts no viewer, only a "
                        "Rerun server that records (`impulse view --headless`)")


def add_service_arguments(parser: argparse.ArgumentParser) -> None:
    """What every service process takes: the run it joins and the router it connects to."""
    add_run_and_connect(parser)


def add_learner_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse learner`: resume, fine-tune, be the hub, and the place in a multi-host group."""
    add_service_arguments(parser)
    parser.add_argument("--resume", action="store_true",
                        help="continue from the newest checkpoint in the run directory (fresh if there is none)")
    parser.add_argument("--init-from", type=Path, metavar="RUN_DIR",
                        help="fine-tune: while the run has no checkpoint of its own, start from the policy of "
                        "RUN_DIR's newest checkpoint (a run directory or a shipped agent such as "
                        "pretrained/general-s), with a fresh optimiser; the [network] section comes from RUN_DIR")
    parser.add_argument("--hub", action="store_true",
                        help="also be the bus hub (listen on bus.hub) when no `impulse launch` provides one")
    parser.add_argument("--host-index", type=int, metavar="N",
                        help="with learner.hosts > 1: this process's place in the learner's group, 0 (the leader, "
                        "which checkpoints and publishes) to hosts-1; under SLURM, SLURM_PROCID by default")


def add_actor_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse actor`: the actor's number."""
    add_service_arguments(parser)
    parser.add_argument("--index", type=int, default=0, metavar="N", help="this actor's number (default 0)")


def add_evaluator_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse evaluator`: the run it joins."""
    add_run_and_connect(parser)


def add_recorder_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse recorder`: the run it joins and the dataset folder."""
    add_run_and_connect(parser)
    parser.add_argument("--out", type=Path, metavar="PATH",
                        help="the dataset folder (instead of recorder.path)")


def add_curriculum_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse curriculum serve|set|get|inspect|inject`."""
    actions = parser.add_subparsers(dest="curriculum_action", metavar="ACTION", required=True)
    serve = actions.add_parser("serve", help="run the curriculum service", allow_abbrev=False)
    add_run_and_connect(serve)
    serve.add_argument("--config", type=Path, metavar="FILE.toml", help="TOML config (without --run)")
    serve.add_argument("--resume", action="store_true", help="continue from the service's newest checkpoint")
    serve.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")

    set_ = actions.add_parser("set", help="change live knobs: KEY=VALUE ... (e.g. replay_prob=0.8)",
                              allow_abbrev=False)
    set_.add_argument("assignments", nargs="+", metavar="KEY=VALUE",
                      help="curriculum knobs, with or without the 'curriculum.' prefix")
    get = actions.add_parser("get", help="print the live knobs", allow_abbrev=False)
    inspect = actions.add_parser("inspect", help="print the level buffer", allow_abbrev=False)
    inspect.add_argument("--top", type=int, default=10, metavar="K", help="levels to list (default 10)")
    inspect.add_argument("--json", action="store_true", help="print the whole report as JSON")
    inspect.add_argument("--render", type=Path, metavar="DIR", help="draw the top K levels as PNG files in DIR")
    inspect.add_argument("--checkpoint", nargs="?", const=-1, type=int, metavar="STEP",
                         help="read the buffer from the run's checkpoint STEP (default: the newest) instead of "
                         "asking the live service")
    inject = actions.add_parser("inject", help="send a level file into the running curriculum's buffer",
                                allow_abbrev=False)
    inject.add_argument("level", type=Path, metavar="LEVEL.json", help="a Kinetix level file")
    for p in (set_, get, inspect, inject):
        add_run_and_connect(p, TOOL_RUN_HELP, required=True)


def add_router_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse router`: where it listens, or list the roles it knows."""
    parser.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help="listen on ENDPOINT instead of router.listen (repeatable), e.g. tls/0.0.0.0:7447")
    parser.add_argument("--roles", action="store_true",
                        help="print the roles whose credentials the router's access control knows, one per line, "
                        "and exit (what deploy/cluster/security/make-test-certs.sh makes credentials for)")


def add_eval_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse eval`: the checkpoint, the levels and attempts, and what to write besides the table."""
    parser.add_argument("--checkpoint", type=Path, required=True, metavar="RUN_DIR",
                        help="a run directory (its newest checkpoint) or one checkpoint's directory")
    parser.add_argument("--levels", metavar="SET",
                        help='"handmade", "kinetix:s|m|l|all" (Kinetix\'s hand-made sets, found as '
                        '$IMPULSE_KINETIX_LEVELS says), a level file, a folder or a glob (default: eval.levels, else '
                        'the training levels)')
    parser.add_argument("--attempts", type=int, metavar="K", help="episodes per level (default: eval.attempts)")
    parser.add_argument("--seed", type=int, default=0, help="evaluation seed (same seed, same numbers)")
    parser.add_argument("--greedy", action="store_true", help="take the most likely action instead of sampling")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the scores as JSON here")
    parser.add_argument("--record", type=Path, metavar="FILE.rrd",
                        help="also play one episode per level and write it to a Rerun recording (open it with "
                        "`rerun FILE.rrd`), drawn as live rollouts are")
    parser.add_argument("--video", type=Path, metavar="FILE.gif|.webp|.mp4",
                        help="also play one episode per level and write them side by side as an animated GIF or "
                        "WebP, or an MP4 (H.264) by the suffix (30 frames per second; a finished level is framed "
                        "green if solved, red if not)")


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse export`: the checkpoint, the new directory and the facts to keep."""
    parser.add_argument("--checkpoint", type=Path, required=True, metavar="RUN_DIR",
                        help="a run directory (its newest checkpoint) or one checkpoint's directory")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="the new, small run directory")
    parser.add_argument("--note", action="append", default=[], metavar="KEY=VALUE",
                        help="a fact to keep with the policy (e.g. commit=abc123), in its counters and "
                        "agent.json")


def add_import_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse import-kinetix`: the Kinetix checkpoint, the run directory and model settings."""
    parser.add_argument("checkpoint", type=Path, metavar="CHECKPOINT",
                        help="a Kinetix checkpoint: full_model.pbz2 (or params.pbz2, model.pbz2) as its training "
                        "scripts save them, a directory holding one, or a pretrained directory (params.safetensors "
                        "+ config.json)")
    parser.add_argument("--out", type=Path, required=True, metavar="RUN_DIR",
                        help="the Impulse run directory to write (must hold no checkpoints yet)")
    parser.add_argument("--kinetix-config", type=Path, metavar="FILE",
                        help="Kinetix config with the model settings, for checkpoints that do not carry them: the "
                        "config.yaml a Kinetix run writes under logs/, or a config.json")
    parser.add_argument("--kinetix-option", action="append", default=[], metavar="KEY=VALUE",
                        help="a Kinetix model setting (repeatable), over the checkpoint's and --kinetix-config's, "
                        "e.g. activation=relu, legacy_entity_id=true, full_attention_mask=true")


def add_levels_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse levels validate|show|render|convert`."""
    actions = parser.add_subparsers(dest="levels_action", metavar="ACTION")

    validate = actions.add_parser(
        "validate", help="check level files and print every problem",
        description="Check level files: the JSON structure, every field's shape and value, roles, bindings, "
        "indices, the fit into --size, and the scene itself. Prints every problem per file; exits 1 if any file "
        "is invalid. Folders are searched for *.json files.",
    )
    validate.add_argument("paths", nargs="+", type=Path, metavar="PATH", help="level files or folders")
    validate.add_argument("--size", choices=SIZE_NAMES, type=str.lower, help="also check that each file fits this size")

    show = actions.add_parser(
        "show", help="describe a level: shapes, roles, joints, thrusters, controls",
        description="Print a readable summary of a level file: its size class, every shape (role, kind, position, "
        "size, fixed or dynamic), joints (type, motor, binding), thrusters and what each action dimension does.",
    )
    show.add_argument("path", type=Path, metavar="FILE")
    show.add_argument("--size", choices=SIZE_NAMES, type=str.lower, help="load into this size first")

    render = actions.add_parser(
        "render", help="draw a level's initial scene as a PNG, or play levels into a video",
        description="Draw the level's initial scene (the 5 m x 5 m arena, y up) as a PNG: shapes in role colours, "
        "fixed shapes darker, joints as dots (fixed joints as squares) and thrusters as triangles pointing the way "
        "they push, coloured by binding. With --video instead: play each level (files, or folders of them) from "
        "its start with the no-op action (motors and thrusters off: the level's own dynamics) for --steps agent "
        "steps and write the episodes side by side as a video, drawn as `impulse eval --video` draws a policy's "
        "episodes (a level whose episode ends holds its last frame, framed green if solved, red if not). To watch "
        "a policy play levels instead: `impulse eval --checkpoint RUN_DIR --levels FILE --video OUT.mp4`.",
    )
    render.add_argument("paths", nargs="+", type=Path, metavar="PATH",
                        help="the level file (with --video: level files or folders of them)")
    written = render.add_mutually_exclusive_group(required=True)
    written.add_argument("-o", "--output", type=Path, metavar="OUT.png", help="PNG file to write")
    written.add_argument("--video", type=Path, metavar="OUT.gif|.webp|.mp4",
                         help="play the levels and write an animated GIF or WebP, or an MP4 (H.264), by the suffix")
    render.add_argument(
        "--scale", type=float,
        help="image size as a multiple of Kinetix's 500 x 500 screen (default 1: 100 pixels per metre; with "
        "--video 0.4 per level, as impulse eval's videos)",
    )
    render.add_argument("--steps", type=int, default=VIDEO_STEPS, metavar="N",
                        help=f"with --video: agent steps to play, at most (default {VIDEO_STEPS}, a training "
                        "episode's length: env.max_timesteps; 30 steps per second of video)")
    render.add_argument("--size", choices=SIZE_NAMES, type=str.lower,
                        help="with --video: load every level into this size (default: the smallest that fits all)")

    convert = actions.add_parser(
        "convert", help="load a level into a size and save it (resize, normalise)",
        description="Load a level file into the given size (at least the file's own size: slots are added, never "
        "removed) and save it in the normalised Kinetix format.",
    )
    convert.add_argument("source", type=Path, metavar="IN")
    convert.add_argument("target", type=Path, metavar="OUT")
    convert.add_argument("--size", choices=SIZE_NAMES, type=str.lower, required=True, help="target size")

    parser.set_defaults(levels_parser=parser)


def add_compare_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse compare`: the runs, the metrics, and the table, plot or identity check."""
    parser.add_argument("runs", nargs="+", type=Path, metavar="RUN_DIR",
                        help="run directories of `impulse train` or `impulse launch` (running ones too)")
    parser.add_argument("--metric", action="append", dest="metrics", metavar="NAME",
                        help="a metrics.jsonl column to compare (repeatable; default: solve_rate, and eval/mean when "
                        "a run has it)")
    parser.add_argument("--by", default="env_steps", metavar="env_steps|time_s|update",
                        help="the x axis of --plot and where the best value is placed (default: env_steps; time_s "
                        "counts seconds since each run's first update)")
    parser.add_argument("--threshold", type=float, metavar="VALUE",
                        help="also show the env steps and time at which each metric first reached VALUE")
    parser.add_argument("--window", metavar="LOW:HIGH",
                        help="also show each metric's mean ± standard error over the rows between LOW and HIGH along "
                        "--by, both included (an end may be left open: 500: or :1250), and how many rows that was")
    parser.add_argument("--plot", type=Path, metavar="FILE.png", help="draw each metric against --by, a line per run")
    parser.add_argument("--json", action="store_true", help="print the comparison as JSON instead of a table")
    parser.add_argument("--identical", type=int, metavar="N",
                        help="instead: check that the runs' first N updates agree bit for bit in every column they "
                        "share (time_s and steps_per_s left out); exit status 1, listing the differences, if not")


def add_studio_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse studio`: where it listens, its levels, the run it shows and its access token."""
    parser.add_argument("--host", default=STUDIO_HOST,
                        help=f"address to listen on (default {STUDIO_HOST}: this machine only; any other address "
                        "needs --token)")
    parser.add_argument("--port", type=int, default=STUDIO_PORT, help=f"port (default {STUDIO_PORT})")
    parser.add_argument("--levels-dir", type=Path, default=STUDIO_LEVELS_DIR, metavar="DIR",
                        help=f"folder the editor saves levels into, shown as the 'saved' set (default "
                        f"./{STUDIO_LEVELS_DIR})")
    parser.add_argument("--levels", action="append", default=[], metavar="SOURCE",
                        help="more levels for the gallery: a level file, a folder of them or a glob pattern "
                        "(repeatable)")
    parser.add_argument("--run", type=Path, metavar="RUN_DIR",
                        help="a run directory (or a checkpoint folder) whose agent the Play page offers to watch; "
                        "when the run has a curriculum service, the Curriculum page shows its buffer and knobs "
                        "and the editor can send levels into its buffer")
    parser.add_argument("--token", metavar="T",
                        help="access token every request must carry (default: a random one made at each start, "
                        "shown in the printed address; required when --host is not loopback); 8 to 200 letters, "
                        "digits or ._~-")
    parser.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                        help="another host name the studio answers to (repeatable): a name you reach it by other "
                        "than localhost, 127.0.0.1, [::1] and --host, such as this machine's name on the network; "
                        "requests naming any other host are refused (DNS rebinding)")


def add_tensorboard_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse tensorboard`: the runs and whether to replace their event files."""
    parser.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR",
                        help="run directories holding a metrics.jsonl")
    parser.add_argument("--replace", action="store_true",
                        help="delete the event files a run's tensorboard/ folder already holds, then write it anew")


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse config describe [KEY]`."""
    actions = parser.add_subparsers(dest="config_action", metavar="ACTION")
    describe = actions.add_parser(
        "describe", help="every key with its type, default and meaning",
        description="Print configuration keys with their type, default and meaning: KEY alone, every key of a "
        "section (ppo, curriculum, ...), or all of them. docs/config.md holds the same reference.")
    describe.add_argument("key", nargs="?", help="a key (ppo.num_envs) or a section (ppo); all when omitted")


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """`impulse view`: the run, the recording and which viewer."""
    parser.add_argument("run", type=Path, metavar="RUN_DIR", help="the run directory (its config.toml names the "
                        "viewer's port: monitor.url)")
    parser.add_argument("--record", type=Path, metavar="FILE.rrd", help="also write everything streamed to FILE.rrd")
    shown = parser.add_mutually_exclusive_group()
    shown.add_argument("--web", action="store_true", help="serve the web viewer even when there is a display")
    shown.add_argument("--native", action="store_true", help="open the native viewer (needs a display)")
    shown.add_argument("--headless", action="store_true",
                       help="no viewer: only the server the run streams to, writing everything to --record FILE.rrd")
    parser.add_argument("--bind", default="127.0.0.1", metavar="HOST",
                        help="address the servers listen on (default 127.0.0.1; 0.0.0.0 exposes them to the network)")
