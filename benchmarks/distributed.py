"""Distributed training against fused training, measured in the same run: how many env steps per second the
learner consumes with 1, 2 and 4 actors, where the gap to fused goes, how many bytes one env step costs on the bus
(and how few it could), and how long a weight broadcast takes to reach the actors.

Parts (all by default; `--parts` picks some):

- `bytes`: the encoded frame of one trajectory batch of a real rollout (one jitted rollout on the size's levels),
  divided by T x E, for sizes S, M, L with the entity observation and with the symbolic (flat) one, multi-discrete
  actions, in the previous padded format, the compact one and the compact one with float16 features
  (`actors.wire`), with the encode and decode cost of each. Each has two floors (see `bytes_floors`) and the ratio
  actual / floor. No processes.
- `runs`: real processes. The fused trainer (`impulse train`) and then `impulse launch` with N actors, on the same
  config (level, network, envs, steps, epochs, minibatches), then the fused trainer once more, so the drift of the
  machine over the runs shows. The rate is read from each run's metrics.jsonl (one line per update, wall-clock
  `time_s`) between update `--skip` and the last one, so compilation and start-up are left out. During a
  distributed run this process watches the status lines on the bus (actor `last_cycle_s`, `sent`, drops,
  `weights_latency_ms`; the learner's lag histogram and drop counts).
- `costs`: in this process, at the run's shapes: one rollout and one `ppo_update` (jitted, as the actor and the
  learner compile them), the serialisation of one batch (actor: `tree_arrays` + pack + `encode`; learner: `decode` +
  unpack + schema check + `tree_from_arrays`, then `device_put`), and the transport of that frame (put -> received
  as bytes in another process, over zenoh with the run's bus settings). With `runs`, one `gap` line per actor
  count then splits the learner's update interval and the actors' cycle into these parts; every derived number
  says how it was derived.

Every line carries the JAX version, backend and device. Timings on a shared CPU are noisy; the two fused runs
bracket the distributed ones to show by how much.

    impulse bench distributed                          # CPU defaults: configs/quick-launch.toml, 1, 2, 4 actors
    impulse bench distributed --actors 1 2 --updates 20
    impulse bench distributed --parts bytes            # bytes per env step only (seconds)
    impulse bench distributed --size s --kinetix-settings --updates 30     # a GPU size: 2,048 envs x 64 steps
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from impulse.benchmarks._harness import LEVELS_DIR, REPO, emit, environment, progress
from impulse.bus.codec import Kind, decode, encode
from impulse.bus.config import BusConfig
from impulse.bus.stamp import Stamp
from impulse.bus.trajectories import decode_trajectory, encode_trajectory
from impulse.deploy.run_config import RunConfig
from impulse.engine.env.actions import action_space
from impulse.engine.env.observations import BASE_SHAPE_FEATURES, symbolic_length
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, Level
from impulse.engine.physics.sizes import SceneSizes, size_preset
from impulse.engine.pytree import tree_arrays

DEFAULT_CONFIG = REPO / "configs" / "quick-launch.toml"
PARTS = ("bytes", "runs", "costs")
NO_CHECKPOINTS = 1_000_000
"""checkpoint.every_updates for the timed runs: no checkpoint is written between two timed updates (fused and
distributed alike; each writes one at the end, after its last metrics line)."""
STATUS_POLL_S = 0.2
STOP_GRACE_S = 60.0
TRANSPORT_MAX_WARMUP = 20
GPU_MEMORY_SHARE = 0.85
"""Distributed runs on one GPU: the learner and the actors split this fraction of its memory (JAX preallocates 75%
per process by default, so a second process would not fit)."""
_INJECTED_PREALLOCATE = False
"""Whether main() turned JAX's preallocation off for this process (then the child processes must not inherit it)."""


# -- configuration ---------------------------------------------------------------------------------------------


def run_overrides(args: argparse.Namespace) -> list[str]:
    """The key=value overrides every timed run gets (fused and distributed), so both train the same thing."""
    overrides = [f"checkpoint.every_updates={NO_CHECKPOINTS}", "eval.attempts=0"]
    if args.size:
        overrides.append(f"env.size={args.size}")
        if not args.levels:
            overrides.append(f"env.levels={LEVELS_DIR / args.size}")
    if args.levels:
        overrides.append(f"env.levels={args.levels}")
    if args.network:
        overrides.append(f"network.kind={args.network}")
        overrides.append(f"env.observation={'symbolic' if args.network == 'flat' else 'entity'}")
    for option, key in (("num_envs", "ppo.num_envs"), ("num_steps", "ppo.num_steps"), ("epochs", "ppo.update_epochs"),
                        ("minibatches", "ppo.num_minibatches"), ("credits", "actors.credits")):
        if getattr(args, option) is not None:
            overrides.append(f"{key}={getattr(args, option)}")
    overrides.extend(args.set)
    return overrides


def resolve(config_path: Path, overrides: list[str]) -> RunConfig:
    from impulse.deploy.config import resolve_config

    return resolve_config(RunConfig, config_path, overrides)


def describe(config: RunConfig) -> dict[str, Any]:
    """The settings a reader needs to match two lines: what was trained, at what batch shape."""
    ppo = config.ppo
    return {"size": config.env.size, "levels": config.env.levels, "observation": config.env.observation,
            "network": config.network.kind, "width": config.network.width, "depth": config.network.depth,
            "num_envs": ppo.num_envs, "num_steps": ppo.num_steps, "update_epochs": ppo.update_epochs,
            "num_minibatches": ppo.num_minibatches}


# -- bytes per env step ----------------------------------------------------------------------------------------


def size_levels(size: str) -> tuple[list[Level], str]:
    """The shared Kinetix levels of a size, else our hand-made ones that fit, and where they came from."""
    from impulse.engine.levels.kinetix_json import load_kinetix_level
    from impulse.engine.levels.sets import load_level_set

    sizes = size_preset(size)
    paths = sorted((LEVELS_DIR / size).glob("*.json")) if LEVELS_DIR.is_dir() else []
    if paths:
        levels = [load_kinetix_level(path, sizes).level for path in paths]
        return levels, f"shared Kinetix levels {size}/ ({len(paths)})"
    names, batch = load_level_set("handmade", sizes)
    return [jax.tree.map(lambda x, i=i: x[i], batch) for i in range(len(names))], \
        f"hand-made levels fitting {size} ({len(names)})"


def active_slots(size: str) -> dict[str, Any]:
    """Mean active polygons, circles, joints and thrusters over the levels of a size (the shared Kinetix levels,
    else our hand-made ones that fit), and the active polygons among those the symbolic vector keeps. The floors
    need them: a batch pads every entity array to the size's slot counts, whatever a level uses."""
    sizes = size_preset(size)
    levels, source = size_levels(size)
    kept = [0, *range(sizes.num_static_polygons, sizes.num_polygons)]
    counts = []
    for level in levels:
        bodies = np.asarray(level.state.bodies.active)
        counts.append((bodies[:sizes.num_polygons].sum(), bodies[sizes.num_polygons:].sum(),
                       np.asarray(level.state.joints.active).sum(), np.asarray(level.state.thrusters.active).sum(),
                       bodies[kept].sum()))
    mean = np.mean(np.asarray(counts, np.float64), axis=0)
    return {"polygons": mean[0], "circles": mean[1], "joints": mean[2], "thrusters": mean[3],
            "kept_polygons": mean[4], "source": source}


def _symbolic_features(sizes: SceneSizes, polygons: float, circles: float, joints: float, thrusters: float) -> float:
    """Features of the symbolic vector for the given row counts (the layout of `engine.env.observations`)."""
    n = sizes.num_bodies
    return (polygons * (BASE_SHAPE_FEATURES + 2 + 2 * sizes.max_polygon_vertices)
            + circles * (BASE_SHAPE_FEATURES + 2)
            + joints * (8 + 10 + NUM_MOTOR_BINDINGS + 2 * n)
            + thrusters * (6 + NUM_THRUSTER_BINDINGS + n) + 1)


def _compact_obs_bits(field: str, shape: tuple[int, ...], active: dict[str, Any], sizes: SceneSizes) -> float:
    """Bits of one observation array of ONE env at one step with inactive slots cut, floats as float16 and
    booleans as bits (integer index arrays keep their dtype)."""
    rows = {"polygons": active["polygons"], "circles": active["circles"], "joints": 2 * active["joints"],
            "thrusters": active["thrusters"]}
    if field in rows:
        return rows[field] * shape[-1] * 16
    if field.endswith("_mask") and field != "attention_mask":
        return rows[field.removesuffix("_mask") + "s"]
    if field == "joint_indexes":
        return 2 * active["joints"] * 2 * 32
    if field == "thruster_indexes":
        return active["thrusters"] * 32
    if field == "attention_mask":
        bodies = active["polygons"] + active["circles"]
        return shape[0] * bodies * bodies
    if field == "obs":  # the symbolic vector: only the rows of active slots
        full = _symbolic_features(sizes, 1 + sizes.num_polygons - sizes.num_static_polygons, sizes.num_circles,
                                  sizes.num_joints, sizes.num_thrusters)
        assert full == symbolic_length(sizes), "the symbolic layout changed: update _symbolic_features"
        return _symbolic_features(sizes, active["kept_polygons"], active["circles"], active["joints"],
                                  active["thrusters"]) * 16
    raise ValueError(f"unknown observation array {field!r}")


def bytes_floors(arrays: dict[str, tuple[tuple[int, ...], np.dtype]], num_envs: int, num_steps: int,
                 active: dict[str, Any], spec: EnvSpec) -> dict[str, Any]:
    """Two floors for the bytes of one env step, from the batch's arrays {name: (shape, dtype)}.

    (a) `compact`: the same fields, but entity arrays cut to the slots levels of this size really use (mean over
    the levels), observation floats as float16, booleans as single bits, no frame header or alignment; the
    bootstrap observation is shared by the T steps of an env. (b) `resimulate`: what a learner that re-simulates
    the episodes itself would need per step: the action as one number over all its joint choices, the reward
    (float32), the done bit and the 64-bit level id."""
    sizes = spec.sizes
    compact_bits = 0.0
    for name, (shape, dtype) in arrays.items():
        if name.startswith("steps/"):
            per, instance = 1.0, shape[2:]
        elif name.startswith("bootstrap_obs"):
            per, instance = 1.0 / num_steps, shape[1:]
        else:  # scalars: behaviour version, actor id, sequence number, once per batch
            per, instance = 1.0 / (num_envs * num_steps), shape
        if name == "train_mask":
            per, instance = 1.0, shape[2:]
        parts = name.split("/")
        if "obs" in parts or parts[0] == "bootstrap_obs":
            field = parts[-1] if parts[-1] != "bootstrap_obs" else "obs"
            bits = _compact_obs_bits(field, instance, active, sizes)
        elif dtype == np.bool_:
            bits = float(math.prod(instance))
        else:
            bits = float(math.prod(instance)) * np.dtype(dtype).itemsize * 8
        compact_bits += per * bits
    space = action_space(spec)
    if space.kind == "continuous":
        action_bits = 16 * len(space.low)
    else:
        action_bits = math.ceil(math.log2(math.prod(space.nvec)))
    resimulate_bits = action_bits + 32 + 1 + 64
    return {
        "compact": compact_bits / 8,
        "resimulate": resimulate_bits / 8,
        "resimulate_action_bits": action_bits,
    }


@functools.cache
def rollout_batch(size: str, observation: str, num_envs: int, num_steps: int) -> tuple[EnvSpec, Any]:
    """A batch of a real rollout on the size's levels (random initial weights, multi-discrete actions), on the
    host: what an actor would send. Kept per arguments for the process (the wire format's tests use the same one:
    a rollout is compiled once)."""
    from impulse.actors.rollout import rollout, start_rollout
    from impulse.actors.trajectory import make_batch
    from impulse.engine.levels.level import stack_levels
    from impulse.learner.agent import make_agent
    from impulse.learner.config import NetworkConfig

    spec = EnvSpec(sizes=size_preset(size), observation=observation, action="multi_discrete")
    agent = make_agent(NetworkConfig(kind="entity" if observation == "entity" else "flat", width=64, depth=2), spec)
    levels = stack_levels(size_levels(size)[0])
    params = agent.init(jax.random.PRNGKey(0))
    carry = start_rollout(spec, EnvParams(), levels, num_envs, jax.random.PRNGKey(1))
    run = jax.jit(lambda p, c: rollout(agent.act, p, spec, EnvParams(), c, levels, num_steps))
    carry, steps, train_mask, episodes, _ = run(params, carry)
    return spec, jax.device_get(make_batch(steps, carry.obs, 1, train_mask=train_mask, episodes=episodes))


def bytes_per_step(size: str, observation: str, num_envs: int, num_steps: int, repeats: int = 5) -> dict[str, Any]:
    """Bytes on the bus per env step of one trajectory batch of a real rollout, with its floors, in three
    formats: `padded` (format 1, the arrays as they are), `compact` (`actors.wire.TrajectoryWire`, exact) and
    `compact_float16` (`bus.wire_float16`). Frames are encoded for real, so header, array table and the 64-byte
    alignment of every array are counted; encode (pack + encode) and decode (decode + unpack + schema check +
    tree_from_arrays) are timed here alone, median of `repeats`."""
    from impulse.actors.wire import TrajectoryWire

    spec, batch = rollout_batch(size, observation, num_envs, num_steps)
    arrays = tree_arrays(batch)
    shapes = {name: (tuple(a.shape), np.dtype(a.dtype)) for name, a in arrays.items()}
    stamp = Stamp("bench", epoch=1, policy_version=1)
    steps = num_envs * num_steps
    obs_bytes = sum(a.nbytes for n, a in arrays.items() if n.startswith("steps/obs"))
    active = active_slots(size)
    floors = bytes_floors(shapes, num_envs, num_steps, active, spec)
    formats: dict[str, Any] = {}
    for label, half in (("padded", None), ("compact", False), ("compact_float16", True)):
        wire = TrajectoryWire(batch, spec.sizes, compact=half is not None, float16=bool(half))

        def send(wire: TrajectoryWire = wire) -> bytearray:
            return encode_trajectory(stamp, wire.pack(tree_arrays(batch)), seq=1, incarnation=1, actor_index=0,
                                     layout=wire.format)

        def receive(frame: bytes, wire: TrajectoryWire = wire) -> Any:
            return wire.checked(decode_trajectory(frame, "bench", len(frame), wire.format).message)
        frame = bytes(send())
        for sent, got in zip(jax.tree.leaves(batch), jax.tree.leaves(receive(frame)), strict=True):
            if not half and not np.array_equal(np.atleast_1d(sent).view(np.uint8), np.atleast_1d(got).view(np.uint8)):
                raise AssertionError(f"{label}: the batch did not come back bit for bit")
        formats[label] = {
            "frame_bytes": len(frame),
            "bytes_per_step": len(frame) / steps,
            "ratio_to_compact": len(frame) / steps / floors["compact"],
            "encode_ms": 1e3 * _median_s(send, repeats),
            "decode_check_ms": 1e3 * _median_s(lambda frame=frame, receive=receive: receive(frame), repeats),
        }
    return {
        "measure": "bytes_per_step",
        "size": size,
        "observation": observation,
        "action": "multi_discrete",
        "num_envs": num_envs,
        "num_steps": num_steps,
        "frame_bytes": formats["compact"]["frame_bytes"],
        "bytes_per_step": formats["compact"]["bytes_per_step"],
        "formats": formats,
        "observation_bytes_per_step": obs_bytes / steps,
        "floor_compact": floors["compact"],
        "ratio_to_compact": formats["compact"]["bytes_per_step"] / floors["compact"],
        "floor_resimulate": floors["resimulate"],
        "ratio_to_resimulate": formats["compact"]["bytes_per_step"] / floors["resimulate"],
        "active_slots": {k: (round(v, 2) if isinstance(v, float) else v) for k, v in active.items()},
        "note": (
            "one batch of a real rollout (random initial weights) on the size's levels; bytes_per_step = encoded "
            "frame length / (T*E) of the format actors send by default (compact, exact); formats: padded = the "
            "previous format, compact_float16 = bus.wire_float16. encode_ms = pack + encode, decode_check_ms = "
            "decode + unpack + schema check + tree_from_arrays, in this process alone (median). floor_compact: "
            "the same fields with entity arrays cut "
            "to the mean active slots of the size's levels (attention mask over active bodies only), observation "
            "floats as float16, booleans as bits, int arrays unchanged, no header or alignment, bootstrap obs "
            "amortised over T. floor_resimulate: action as one number over all choices "
            f"({floors['resimulate_action_bits']} bits) + reward float32 + done bit + 64-bit level id, if the "
            "learner re-simulated episodes itself (it would also need the reset keys, and the behaviour log-probs "
            "and values recomputed from the behaviour weights); sending the level id once per episode instead of "
            "per step would lower it further."
        ),
    }


# -- processes -------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class RunResult:
    """What one timed run left behind: its metrics lines, the status lines seen on the bus, and its cost."""

    system: str
    actors: int
    records: list[dict[str, Any]]
    statuses: list[tuple[float, str, dict[str, Any]]]
    wall_s: float
    returncode: int
    load_avg: tuple[float, float]
    log: Path
    memory: dict[str, str] = dataclasses.field(default_factory=dict)
    """Allocator settings given to the run's processes (GPU only)."""


def _read_metrics(path: Path) -> list[dict[str, Any]]:
    import json

    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _stop(process: subprocess.Popen) -> None:
    """Stop a run we started: SIGTERM to its process group (the launcher stops its children itself), then
    SIGKILL to the group if it does not end in time."""
    if process.poll() is not None:
        return
    try:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    except ProcessLookupError:
        pass


TIMED_OUT = 124


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a timed run: ours, without the allocator setting this process gave itself (the runs
    use JAX's defaults unless the caller set one), plus `extra`."""
    env = dict(os.environ)
    if _INJECTED_PREALLOCATE:
        env.pop("XLA_PYTHON_CLIENT_PREALLOCATE", None)
    env.update(extra or {})
    return env


def run_process(argv: list[str], log: Path, timeout_s: float, env: dict[str, str],
                on_poll: Callable[[], None] | None = None) -> tuple[int, float]:
    """Run one `impulse` command in its own process group (so a timeout can stop all it started), calling
    `on_poll` every STATUS_POLL_S while it runs. Returns (exit status, or TIMED_OUT; wall seconds)."""
    start = time.perf_counter()
    timed_out = False
    with log.open("w") as out:
        process = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=REPO,
                                   start_new_session=True)
        try:
            while process.poll() is None:
                if on_poll is not None:
                    on_poll()
                if time.perf_counter() - start > timeout_s:
                    progress(f"  timed out after {timeout_s:.0f} s: stopping it")
                    timed_out = True
                    break
                time.sleep(STATUS_POLL_S)
            if on_poll is not None:
                on_poll()
        finally:
            _stop(process)
    return (TIMED_OUT if timed_out else process.returncode), time.perf_counter() - start


def _fail(result: RunResult, what: str) -> None:
    tail = "\n".join(result.log.read_text().splitlines()[-30:]) if result.log.is_file() else ""
    progress(f"{what} failed (exit status {result.returncode}); last lines of {result.log}:\n{tail}")


def run_fused(config_path: Path, overrides: list[str], work: Path, updates: int, steps_per_update: int,
              timeout_s: float, label: str) -> RunResult:
    """`impulse train` as a child process, exactly as a user runs it, for `updates` updates."""
    run_dir = work / label
    argv = [sys.executable, "-m", "impulse.deploy.cli", "train", "--config", str(config_path), *overrides,
            f"name=bench-{label}", f"run_dir={run_dir}", f"total_env_steps={updates * steps_per_update}"]
    load = os.getloadavg()[0]
    code, wall = run_process(argv, work / f"{label}.log", timeout_s, child_env())
    return RunResult("impulse-fused", 0, _read_metrics(run_dir / "metrics.jsonl"), [], wall, code,
                     (load, os.getloadavg()[0]), work / f"{label}.log")


def free_endpoint() -> str:
    from impulse.benchmarks.bus_copies import free_endpoint as free

    return free()


def run_distributed(config_path: Path, overrides: list[str], work: Path, updates: int, steps_per_update: int,
                    num_actors: int, timeout_s: float) -> RunResult:
    """`impulse launch` with `num_actors` actors as a child process, on a free loopback port, while this process
    watches every status line on the run's bus (kept with the time it arrived)."""
    from impulse.bus.codec import Rejected
    from impulse.bus.keys import OPERATOR
    from impulse.bus.session import Bus
    from impulse.bus.status import read_status

    label = f"distributed-{num_actors}"
    run_dir = work / label
    name = f"bench-dist-{num_actors}-{os.getpid()}"
    extra = [f"name={name}", f"run_dir={run_dir}", f"actors.num_actors={num_actors}",
             f"total_env_steps={updates * steps_per_update}", f"bus.hub={free_endpoint()}"]
    config = resolve(config_path, [*overrides, *extra])
    argv = [sys.executable, "-m", "impulse.deploy.cli", "launch", "--config", str(config_path), *overrides, *extra,
            "--status-every", "30"]
    memory = {}
    if "XLA_PYTHON_CLIENT_MEM_FRACTION" not in os.environ and jax.default_backend() == "gpu":
        memory["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{GPU_MEMORY_SHARE / (num_actors + 1):.3f}"
    env = child_env(memory)
    statuses: list[tuple[float, str, dict[str, Any]]] = []
    load = os.getloadavg()[0]
    with Bus(config.bus, config.name, OPERATOR, "bench-watcher") as bus:
        inbox = bus.inbox(bus.keys.status_pattern(), 256, drop_oldest=True)

        def collect() -> None:
            for received in inbox.poll():
                try:
                    heard = read_status(received, bus.keys)
                except Rejected:
                    continue
                statuses.append((time.time(), f"{heard.role}/{heard.ident}", heard.status))

        code, wall = run_process(argv, work / f"{label}.log", timeout_s, env, collect)
    return RunResult("impulse-distributed", num_actors, _read_metrics(run_dir / "metrics.jsonl"), statuses, wall,
                     code, (load, os.getloadavg()[0]), work / f"{label}.log", memory)


# -- reading the runs ------------------------------------------------------------------------------------------


def steady_window(records: list[dict[str, Any]], skip: int) -> dict[str, Any]:
    """Consumed env steps/s from the wall-clock `time_s` of update `skip` to that of the last update: the first
    updates carry compilation, process start-up and the actors' first batches arriving together."""
    updates = [r for r in records if "update" in r and "time_s" in r]
    if len(updates) < skip + 2:
        raise ValueError(f"only {len(updates)} updates were recorded; need more than skip + 1 = {skip + 1}")
    first, window = updates[skip - 1], updates[skip:]
    last = window[-1]
    seconds = last["time_s"] - first["time_s"]
    times = [first["time_s"]] + [r["time_s"] for r in window]
    intervals = np.diff(times)
    lags = [int(r["policy_lag"]) for r in window if "policy_lag" in r]
    queues = [r["queue"] for r in window if "queue" in r]
    steps = last["env_steps"] - first["env_steps"]
    return {
        "env_steps_per_s": steps / seconds,
        "env_steps_per_s_median_interval": steps / len(window) / float(np.median(intervals)),
        "updates_timed": len(window),
        "window": (first["time_s"], last["time_s"]),
        "interval_s": {"mean": float(intervals.mean()), "median": float(np.median(intervals)),
                       "max": float(intervals.max())},
        "lags": lags,
        "queue_mean": float(np.mean(queues)) if queues else None,
        "queue_nonempty_fraction": float(np.mean([q > 0 for q in queues])) if queues else None,
    }


def lag_summary(values: list[int]) -> dict[str, Any]:
    if not values:
        return {}
    return {"mean": float(np.mean(values)), "max": int(max(values)),
            "histogram": {str(k): v for k, v in sorted(Counter(values).items())}}


def last_statuses(statuses: list[tuple[float, str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """The newest status of each process ("learner/learner", "actor/actor-0", ...)."""
    newest: dict[str, dict[str, Any]] = {}
    for _, sender, status in statuses:
        newest[sender] = status
    return newest


def actor_window(statuses: list[tuple[float, str, dict[str, Any]]], window: tuple[float, float],
                 steps_per_batch: int) -> dict[str, dict[str, Any]]:
    """Per actor, over the learner's steady window: the median `last_cycle_s` (rollout, device_get, encode,
    put; measured by the actor) and the period between two sent batches (from its `sent` counter over the
    window), whose difference is the time it spent waiting (for credit or weights)."""
    start, end = window
    per_actor: dict[str, list[tuple[float, dict[str, Any]]]] = {}
    for received, sender, status in statuses:
        if sender.startswith("actor/") and start <= received <= end:
            per_actor.setdefault(sender.split("/", 1)[1], []).append((received, status))
    summary = {}
    for name, seen in sorted(per_actor.items()):
        cycles = [s["last_cycle_s"] for _, s in seen if s.get("last_cycle_s")]
        (t0, s0), (t1, s1) = seen[0], seen[-1]
        sent = s1.get("sent", 0) - s0.get("sent", 0)
        period = (t1 - t0) / sent if sent > 0 else None
        cycle = statistics.median(cycles) if cycles else None
        summary[name] = {
            "cycle_s_median": cycle,
            "rollout_steps_per_s_in_run": steps_per_batch / cycle if cycle else None,
            "period_s": period,
            "wait_s": period - cycle if period and cycle else None,
            "status_samples": len(seen),
        }
    return summary


def distributed_record(result: RunResult, skip: int, fused_rate: float | None, config: RunConfig) -> dict:
    """One throughput line of a distributed run: rate, ratio to fused, policy lag and every drop counter."""
    window = steady_window(result.records, skip)
    newest = last_statuses(result.statuses)
    learner = newest.get("learner/learner", {})
    actors = {sender.split("/", 1)[1]: s for sender, s in newest.items() if sender.startswith("actor/")}
    all_lags = [int(r["policy_lag"]) for r in result.records if "policy_lag" in r]
    return {
        "measure": "throughput",
        "system": "impulse-distributed",
        "actors": result.actors,
        "credits": config.actors.credits,
        "when_no_credit": config.actors.when_no_credit,
        **describe(config),
        "env_steps_per_s": window["env_steps_per_s"],
        "env_steps_per_s_median_interval": window["env_steps_per_s_median_interval"],
        "ratio_to_fused": window["env_steps_per_s"] / fused_rate if fused_rate else None,
        "skip_updates": skip,
        "updates_timed": window["updates_timed"],
        "interval_s": window["interval_s"],
        "policy_lag": lag_summary(window["lags"]),
        "policy_lag_all_updates": lag_summary(all_lags),
        "learner_queue_mean": window["queue_mean"],
        "learner_queue_nonempty_fraction": window["queue_nonempty_fraction"],
        "learner_status": {key: learner.get(key, 0 if learner else None) for key in (
            "lag_histogram", "dropped_stale", "dropped_old_epoch", "dropped_overflow", "lost", "rejected",
            "consumed_steps_per_s", "weights_published")},
        "actor_status": {name: {key: s.get(key) for key in ("sent", "dropped_no_credit", "written_off",
                                                            "weights_adopted", "rejected")}
                         for name, s in sorted(actors.items())},
        "run_wall_s": result.wall_s,
        "load_avg_1m": list(result.load_avg),
        **({"process_env": result.memory} if result.memory else {}),
        "note": ("env_steps_per_s from metrics.jsonl time_s (learner wall clock at the end of each update) between "
                 "update skip_updates and the last; policy_lag from metrics.jsonl; drop counts from the final "
                 "status lines on the bus (up to bus.status_every_s old; absent counters are 0)"),
    }


def weights_record(result: RunResult, weights_bytes: int | None, config: RunConfig) -> dict[str, Any]:
    """Publish-to-adopted latency of weight broadcasts per actor, from each actor's last status line."""
    newest = last_statuses(result.statuses)
    per_actor = {sender.split("/", 1)[1]: s.get("weights_latency_ms") for sender, s in sorted(newest.items())
                 if sender.startswith("actor/")}
    return {
        "measure": "weights_latency",
        "actors": result.actors,
        "per_actor_ms": per_actor,
        "p50_ms_max_over_actors": max((v["p50"] for v in per_actor.values() if v), default=None),
        "max_ms": max((v["max"] for v in per_actor.values() if v), default=None),
        "weights_frame_bytes": weights_bytes,
        "publish_every": config.learner.publish_every,
        "note": ("from the actors' status weights_latency_ms (the last 100 broadcasts each adopted: wall clock at "
                 "adoption minus the learner's published_at). Actors adopt weights only between rollouts, so this "
                 "includes waiting for the rollout in progress to end, not only transport; broadcasts superseded "
                 "before adoption are not counted"),
    }


# -- in-process costs ------------------------------------------------------------------------------------------


def _median_s(fn: Callable[[], Any], repeats: int) -> float:
    jax.block_until_ready(fn())
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return statistics.median(runs)


def inprocess_costs(config: RunConfig, repeats: int) -> dict[str, Any]:
    """One rollout, one `ppo_update`, and the serialisation of one batch, timed here alone at the run's shapes
    (jitted as the actor and the learner jit them). In the runs these compete with other processes for the same
    cores, so they are lower bounds for what the processes spend."""
    from impulse.actors.levels import LocalLevels
    from impulse.actors.rollout import rollout, start_rollout
    from impulse.actors.trajectory import make_batch
    from impulse.actors.wire import TrajectoryWire, trajectory_template, weights_hash
    from impulse.bus.weights import encode_weights
    from impulse.engine.env.spec import env_from_config
    from impulse.engine.pytree import tree_arrays
    from impulse.learner.agent import make_agent
    from impulse.learner.update import TrainState, make_optimizer, ppo_update

    ppo = config.ppo
    spec, env_params = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    key = jax.random.PRNGKey(0)
    first = LocalLevels(config.env, spec.sizes).next_batch(key).levels
    params = agent.init(jax.random.PRNGKey(config.seed))
    roll = jax.jit(lambda p, c, lv: rollout(agent.act, p, spec, env_params, c, lv, ppo.num_steps), donate_argnums=1)
    held = {"carry": start_rollout(spec, env_params, first, ppo.num_envs, key)}

    def one_rollout() -> Any:
        held["carry"], steps, train_mask, _, _ = roll(params, held["carry"], first)
        held["steps"], held["train_mask"] = steps, train_mask
        return steps

    start = time.perf_counter()
    jax.block_until_ready(one_rollout())
    rollout_compile_s = time.perf_counter() - start
    rollout_s = _median_s(one_rollout, repeats)
    batch = jax.device_get(make_batch(held["steps"], held["carry"].obs, 0, train_mask=held["train_mask"]))

    weights = encode_weights(Stamp("bench"), tree_arrays(params), weights_hash(params))  # before donation
    optimizer = make_optimizer(ppo, 1000)
    update = jax.jit(lambda state, b, k: ppo_update(state, b, k, apply_fn=agent.apply,
                                                    distribution=agent.distribution, optimizer=optimizer,
                                                    config=ppo), donate_argnums=0)
    train = {"state": TrainState(params, optimizer.init(params), np.asarray(0, np.int32))}
    device_batch = jax.device_put(batch)

    def one_update() -> Any:
        train["state"], losses = update(train["state"], device_batch, jax.random.PRNGKey(1))
        return losses

    start = time.perf_counter()
    jax.block_until_ready(one_update())
    update_compile_s = time.perf_counter() - start
    update_s = _median_s(one_update, repeats)

    template = trajectory_template(spec, ppo.num_envs, ppo.num_steps)
    wire = TrajectoryWire(template, spec.sizes, compact=config.bus.wire_compact,
                          float16=config.bus.wire_float16)
    run = "bench"

    stamp = Stamp(run, epoch=1, policy_version=1)

    def actor_encode() -> bytearray:
        return encode_trajectory(stamp, wire.pack(tree_arrays(batch)), seq=1, incarnation=1, actor_index=0,
                                 layout=wire.format)

    frame = bytes(actor_encode())
    message = decode(frame, run=run, kinds=Kind.TRAJECTORY)

    def learner_decode() -> Any:
        return wire.checked(decode_trajectory(frame, run, len(frame), wire.format).message)

    received = learner_decode()
    return {
        "rollout_s": rollout_s,
        "rollout_compile_s": rollout_compile_s,
        "update_s": update_s,
        "update_compile_s": update_compile_s,
        "encode_ms": 1e3 * _median_s(actor_encode, repeats),
        "decode_check_ms": 1e3 * _median_s(learner_decode, repeats),
        "device_put_ms": 1e3 * _median_s(lambda: jax.device_put(received), repeats),
        "frame_bytes": len(frame),
        "arrays": dict(message.arrays),
        "weights_bytes": len(weights),
    }


def transport_ms(arrays: dict[str, np.ndarray], bus_config: BusConfig, repeats: int) -> dict[str, Any]:
    """Put -> received as bytes of one trajectory frame into another process over zenoh on loopback, one message
    at a time, sent with the run's bus settings (shared memory, pool size); the receiver of
    `benchmarks.bus_copies` acknowledges each with its monotonic receive time."""
    from impulse.benchmarks.bus_copies import RUN, receiver_link, timed_put
    from impulse.bus.session import Bus

    frame = encode(Kind.TRAJECTORY, arrays, run=RUN)
    endpoint = free_endpoint()
    shared_memory = bus_config.shared_memory
    sender = dataclasses.replace(bus_config, hub=endpoint, connect=())
    with Bus(sender, RUN, "actor", "bench", listen=True) as bus, receiver_link(bus, endpoint, shared_memory,
                                                                               4) as (publisher, acks):
        def one() -> tuple[float, bool]:
            fields = timed_put(publisher, acks, frame)
            return (fields["received_ns"] - fields["sent_ns"]) / 1e6, bool(fields["via_shm"])

        # Zenoh sends the first few large messages of a new link over the socket (5 here) before its shared
        # memory is set up; a run sends hundreds, so those are a start-up cost, reported apart.
        warmup = [one()]
        while shared_memory and not warmup[-1][1] and len(warmup) < TRANSPORT_MAX_WARMUP:
            warmup.append(one())
        measured = [one() for _ in range(repeats)]
        latencies = [ms for ms, _ in measured]
        through_shm = sum(shm for _, shm in measured)
    return {"median_ms": statistics.median(latencies), "max_ms": max(latencies), "bytes": len(frame),
            "shared_memory": shared_memory, "shm_pool_mib": bus_config.shm_pool_mib,
            "through_shm": f"{through_shm}/{repeats}",
            "first_messages_ms": [round(ms, 2) for ms, _ in warmup]}


def gap_record(result: RunResult, fused: dict[str, Any], costs: dict[str, Any], transport: dict[str, Any],
               skip: int, config: RunConfig) -> dict[str, Any]:
    """Where the time of one distributed update goes, next to one fused iteration.

    Learner: its steady interval between updates (measured) = update compute + ingest of one batch (decode,
    schema check, device_put) + the rest, which is idle time (waiting for a batch) or the update slowed by the
    actors sharing the machine: the two are told apart by the queue (a batch already waiting means the learner
    did not wait). Actors: their period between batches = the cycle they measure (rollout, device_get, encode,
    put) + the wait for credit."""
    window = steady_window(result.records, skip)
    steps_per_batch = config.ppo.num_envs * config.ppo.num_steps
    interval = window["interval_s"]["median"]
    ingest_s = (costs["decode_check_ms"] + costs["device_put_ms"]) / 1e3
    rest = interval - costs["update_s"] - ingest_s
    actors = actor_window(result.statuses, window["window"], steps_per_batch)
    serial_s = (costs["encode_ms"] + costs["decode_check_ms"] + costs["device_put_ms"]) / 1e3
    ideal = steps_per_batch / max(costs["update_s"] + ingest_s,
                                  (costs["rollout_s"] + costs["encode_ms"] / 1e3) / max(result.actors, 1))
    return {
        "measure": "gap",
        "actors": result.actors,
        **describe(config),
        "fused_interval_s": fused["interval_s"],
        "fused_isolated_rollout_plus_update_s": costs["rollout_s"] + costs["update_s"],
        "distributed_interval_s": interval,
        "learner": {
            "update_s_isolated": costs["update_s"],
            "ingest_s_isolated": ingest_s,
            "idle_or_contention_s": rest,
            "idle_or_contention_share": rest / interval,
            "queue_nonempty_fraction": window["queue_nonempty_fraction"],
        },
        "actors_in_run": actors,
        "actor_rollout_s_isolated": costs["rollout_s"],
        "serialisation_ms": {"encode": costs["encode_ms"], "decode_check": costs["decode_check_ms"],
                             "device_put": costs["device_put_ms"], "total": 1e3 * serial_s,
                             "share_of_fused_interval": serial_s / fused["interval_s"]},
        "transport_ms": transport,
        "frame_bytes": costs["frame_bytes"],
        "ideal_overlap_env_steps_per_s": ideal,
        "derivation": (
            "distributed_interval_s and fused_interval_s: median gap between consecutive metrics.jsonl time_s over "
            "the steady window (measured; fused: mean of the fused runs' medians; medians, so that stalls caused "
            "by other load on the machine do not count). update_s_isolated, ingest_s_isolated (decode + schema "
            "check + tree_from_arrays + device_put), actor_rollout_s_isolated, serialisation and transport: timed "
            "in this process alone after the runs (measured, but without other processes competing). "
            "idle_or_contention_s = interval - update - ingest (derived): learner time its own isolated work does "
            "not explain, i.e. waiting for a batch or slowed by sharing the machine; queue_nonempty_fraction (the "
            "share of updates after which another batch was already waiting) near 1 means it was not waiting "
            "(uninformative when actors x credits = 1: the queue then never holds a second batch). "
            "actors_in_run: cycle_s_median = the actor's own last_cycle_s status samples in the window (measured: "
            "rollout + device_get + encode + put); period_s = window time / batches it sent in the window (from "
            "its sent counter; derived); wait_s = period - cycle (derived: waiting for credit or weights). "
            "ideal_overlap_env_steps_per_s = E*T / max(update + ingest, (rollout + encode) / actors) from the "
            "isolated costs: the rate if the learner and each actor had hardware of their own and transport were "
            "free (a model, not a measurement)."
        ),
    }


# -- main ------------------------------------------------------------------------------------------------------


def measure_bytes(args: argparse.Namespace, env_info: dict[str, str]) -> None:
    for size in args.bytes_sizes:
        for observation in ("entity", "symbolic"):
            progress(f"bytes per env step: size {size}, {observation} observation ...")
            emit({**bytes_per_step(size, observation, args.bytes_envs, args.bytes_steps, args.repeats),
                  **env_info})


def measure_runs(args: argparse.Namespace, config_path: Path, overrides: list[str], config: RunConfig,
                 work: Path, env_info: dict[str, str]) -> tuple[list[RunResult], dict[str, Any] | None]:
    """Fused, then each actor count, then fused again; emits one throughput line per run and a summary."""
    steps_per_update = config.ppo.num_envs * config.ppo.num_steps
    fused_runs: list[dict[str, Any]] = []
    distributed: list[RunResult] = []

    def fused(label: str) -> None:
        progress(f"fused run ({label}): {args.updates} updates of {steps_per_update} env steps ...")
        result = run_fused(config_path, overrides, work, args.updates, steps_per_update, args.timeout, label)
        if result.returncode != 0:
            _fail(result, "the fused run")
            return
        window = steady_window(result.records, args.skip)
        fused_runs.append(window)
        emit({"measure": "throughput", "system": "impulse-fused", "run": label, **describe(config),
              "env_steps_per_s": window["env_steps_per_s"],
              "env_steps_per_s_median_interval": window["env_steps_per_s_median_interval"], "skip_updates": args.skip,
              "updates_timed": window["updates_timed"], "interval_s": window["interval_s"],
              "run_wall_s": result.wall_s, "load_avg_1m": list(result.load_avg), **env_info})

    fused("fused-before")
    fused_rate = fused_runs[0]["env_steps_per_s"] if fused_runs else None
    for num_actors in args.actors:
        progress(f"distributed run: learner + {num_actors} actor(s), {args.updates} updates ...")
        result = run_distributed(config_path, overrides, work, args.updates, steps_per_update, num_actors,
                                 args.timeout)
        if result.returncode != 0:
            _fail(result, f"the distributed run with {num_actors} actors")
            continue
        try:
            emit({**distributed_record(result, args.skip, fused_rate, config), **env_info})
        except ValueError as err:
            _fail(result, f"the distributed run with {num_actors} actors ({err})")
            continue
        distributed.append(result)
    if not args.no_fused_after:
        fused("fused-after")
    if not fused_runs:
        return distributed, None
    rates = [f["env_steps_per_s"] for f in fused_runs]
    robust = [f["env_steps_per_s_median_interval"] for f in fused_runs]
    mean_fused = {"env_steps_per_s": float(np.mean(rates)),
                  "interval_s": float(np.mean([f["interval_s"]["median"] for f in fused_runs]))}
    windows = {str(r.actors): steady_window(r.records, args.skip) for r in distributed}
    emit({"measure": "throughput_summary", **describe(config), "fused_env_steps_per_s": rates,
          "fused_env_steps_per_s_median_interval": robust,
          "fused_drift": (rates[-1] / rates[0] - 1) if len(rates) > 1 else None,
          "ratio_to_fused_mean": {n: w["env_steps_per_s"] / mean_fused["env_steps_per_s"] for n, w in windows.items()},
          "ratio_to_fused_mean_median_interval": {n: w["env_steps_per_s_median_interval"] / float(np.mean(robust))
                                                  for n, w in windows.items()},
          "note": ("fused measured before and after the distributed runs; the drift between them shows the noise. "
                   "*_median_interval: steps per update / median update interval, which a few stalls caused by "
                   "other load on the machine do not move"),
          **env_info})
    return distributed, mean_fused


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench distributed", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", default=list(PARTS), choices=PARTS)
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                        help="run config for fused and distributed runs (default configs/quick-launch.toml)")
    parser.add_argument("--actors", nargs="+", type=int, default=[1, 2, 4], help="actor counts (default 1 2 4)")
    parser.add_argument("--updates", type=int, default=30, help="updates per timed run (default 30)")
    parser.add_argument("--skip", type=int, default=5, help="updates left out of the timing (default 5)")
    parser.add_argument("--size", choices=["s", "m", "l"],
                        help="scene size; the levels become all shared Kinetix levels of the size (as in "
                        "benchmarks.train) unless --levels says otherwise")
    parser.add_argument("--levels", help="env.levels for the runs")
    parser.add_argument("--network", choices=["entity", "transformer", "flat"])
    parser.add_argument("--num-envs", type=int)
    parser.add_argument("--num-steps", type=int)
    parser.add_argument("--epochs", type=int)
    parser.add_argument("--minibatches", type=int)
    parser.add_argument("--credits", type=int, help="actors.credits (batches in flight per actor)")
    parser.add_argument("--kinetix-settings", action="store_true",
                        help="2,048 envs x 64 steps, 8 epochs, 32 minibatches (Kinetix's PPO benchmark; a GPU size)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="any other config override for every run (repeatable)")
    parser.add_argument("--bytes-sizes", nargs="+", default=["s", "m", "l"], choices=["s", "m", "l"])
    parser.add_argument("--bytes-envs", type=int, default=64, help="E of the batch whose frame is measured")
    parser.add_argument("--bytes-steps", type=int, default=64, help="T of the batch whose frame is measured")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of each in-process timing")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds before a run is stopped")
    parser.add_argument("--no-fused-after", action="store_true", help="skip the second fused run")
    parser.add_argument("--keep", action="store_true", help="keep the run directories and logs")
    args = parser.parse_args(argv)
    if args.kinetix_settings:
        args.num_envs, args.num_steps, args.epochs, args.minibatches = 2048, 64, 8, 32
    if args.skip < 1 or args.updates < args.skip + 3:
        parser.error("need --skip >= 1 and --updates >= --skip + 3")
    # Timed runs start their own JAX processes: this one must not take the GPU's memory first.
    global _INJECTED_PREALLOCATE
    if "XLA_PYTHON_CLIENT_PREALLOCATE" not in os.environ:
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
        _INJECTED_PREALLOCATE = True
    # `timeout` and the like send SIGTERM: end through the `finally` blocks, which stop the runs we started.
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    env_info = environment()
    if "bytes" in args.parts:
        measure_bytes(args, env_info)
    if "runs" not in args.parts and "costs" not in args.parts:
        return 0

    overrides = run_overrides(args)
    config = resolve(args.config, overrides)
    work = Path(tempfile.mkdtemp(prefix="impulse-bench-distributed-"))
    try:
        distributed, fused = ([], None)
        if "runs" in args.parts:
            distributed, fused = measure_runs(args, args.config, overrides, config, work, env_info)
        if "costs" not in args.parts:
            return 0
        progress("in-process costs: rollout, update, serialisation, transport ...")
        from impulse.deploy.runtime.compile_cache import enable_compile_cache

        enable_compile_cache()  # the checkout's cache, which the runs above filled with the same programs
        costs = inprocess_costs(config, args.repeats)
        transport = transport_ms(costs["arrays"], config.bus, max(args.repeats, 10))
        emit({"measure": "costs", **describe(config),
              **{k: v for k, v in costs.items() if k != "arrays"},
              "transport_ms": transport,
              "note": ("timed in this process alone at the run's shapes: rollout and ppo_update jitted as the actor "
                       "and the learner jit them (median of repeats); encode = tree_arrays + pack + encode; "
                       "decode_check = decode + unpack + schema check + tree_from_arrays; transport = put -> received "
                       "as bytes in another process over zenoh on loopback (benchmarks.bus_copies receiver), one "
                       "message at a time once zenoh's shared memory is in use; first_messages_ms are the ones before "
                       "that"),
              **env_info})
        for result in distributed:
            if fused is not None:
                emit({**gap_record(result, fused, costs, transport, args.skip, config), **env_info})
            emit({**weights_record(result, costs["weights_bytes"], config), **env_info})
    finally:
        if args.keep:
            progress(f"run directories and logs kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
