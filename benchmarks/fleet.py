"""A synthetic fleet of actors against a real curriculum service or a real learner: what N actors cost them.

`--against curriculum` (the default) starts a real `impulse curriculum serve` (random levels, the config's
curriculum and batch size) behind a zenoh hub on loopback, then for each fleet size N plays N actors as zenoh
sessions spread over a few processes. Each actor asks for a level batch (`levels_sample`, one batch of
`ppo.num_envs` levels, as a real actor does before every rollout) every `--period` seconds, starting at a random
phase, and times the answer; with `--results` it then publishes made-up results for the batch's levels, as an
actor does after its rollout, so that the service scores levels, fills its buffer and replays. Per N, one JSON
line: requests answered per second, latency p50/p90/p99/max, requests that got no answer in time, the service's
resident memory, and from its status lines the results it applied, the new and replayed batches it served and the
filtered and unfiltered batches of new levels it made.

`--against learner` starts a real `impulse learner` (the config's network, PPO settings and wire format) and
records one real trajectory batch: a rollout of the config's agent (random initial weights) on random levels,
packed in the run's wire format once. Each synthetic actor then does on the bus what `actors.process.Actor` does:
it follows the learner's weights (their epoch and version stamp its frames), sends a frame every `--period`
seconds while it holds a credit (at most `actors.credits` unacknowledged; out of credit, that send is skipped and
counted) and reads the learner's acknowledgements. Per N, one JSON line: frames offered, sent and acknowledged per
second; the time from publishing a frame to its acknowledgement (the learner acknowledges a frame when it takes it
for an update); sends skipped for want of credit; and from the learner's status lines, its updates and env steps
consumed per second, the frames and MB it took in per second, the time its thread spent on them (taking each out
of zenoh and reading its header; unpacking and checking those it trains on), the env steps per second that time
would allow a learner doing nothing else, its queue, drops by reason, and its memory (private and shared pages).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from impulse.benchmarks._harness import REPO, emit, progress

DEFAULT_CONFIG = REPO / "configs" / "quick-launch.toml"
RUN = "fleet"
TIMEOUT_S = 10.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def memory_mib(pid: int) -> dict[str, float]:
    """A process's resident memory split into its own (private pages) and pages it shares with other processes
    (zenoh's shared-memory pools of the senders it reads from, libraries), in MiB."""
    fields: dict[str, float] = {}
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]:
        name, _, value = line.partition(":")
        fields[name] = int(value.split()[0]) / 1024
    return {"rss": fields.get("Rss", 0.0),
            "private": fields.get("Private_Clean", 0.0) + fields.get("Private_Dirty", 0.0),
            "shared": fields.get("Shared_Clean", 0.0) + fields.get("Shared_Dirty", 0.0)}


def open_actor_sessions(hub: str, names: list[str]) -> list[Any]:
    """An open bus session of the actor role per name, connected to `hub`."""
    from impulse.bus.config import BusConfig
    from impulse.bus.keys import ACTOR
    from impulse.bus.session import Bus

    config = BusConfig(connect=(hub,), hub=hub)
    sessions = [Bus(config, RUN, ACTOR, name) for name in names]
    for session in sessions:
        session.__enter__()
    return sessions


def run_each(sessions: list[Any], actor: Any) -> None:
    """`actor(session)` for every session, each on a thread of its own, until all return; then close them."""
    threads = [threading.Thread(target=actor, args=(session,), daemon=True) for session in sessions]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for session in sessions:
        session.__exit__(None, None, None)


def play_fleet(target: Any, arguments: Any, actors: int, processes: int, service_pid: int
               ) -> tuple[list[Any], list[dict[str, float]]]:
    """`target(*arguments(share), out)` in up to `processes` spawned processes, the actors dealt among them; returns
    what each put on `out`, and the service's memory (`memory_mib`) sampled every 2 s meanwhile."""
    context = multiprocessing.get_context("spawn")
    out = context.Queue()
    names = [f"actor-{i}" for i in range(actors)]
    shares = [names[i::processes] for i in range(min(processes, actors))]
    workers = [context.Process(target=target, args=(*arguments(share), out)) for share in shares]
    for worker in workers:
        worker.start()
    memory = [memory_mib(service_pid)]
    results: list[Any] = []
    while len(results) < len(workers):
        try:
            results.append(out.get(timeout=2.0))
        except Exception:  # noqa: BLE001 - queue.Empty: sample the service's memory meanwhile
            memory.append(memory_mib(service_pid))
    for worker in workers:
        worker.join(timeout=30)
    return results, memory


def level_results(payload: bytes, rng: random.Random) -> dict[str, np.ndarray]:
    """Made-up results for the levels of a LEVELS reply, as an actor would send them after its rollout: two
    episodes per level, none, one or both solved (so that learnability varies), by policy version 0."""
    from impulse.bus.codec import Kind, decode

    level_id = np.asarray(decode(payload, run=RUN, kinds=Kind.LEVELS).arrays["levels/level_id"])
    k = level_id.shape[0]
    solved = np.asarray([rng.choice((0, 1, 2)) for _ in range(k)], np.int32)
    return {"level_id": level_id, "episodes": np.full(k, 2, np.int32), "solved": solved,
            "return_sum": solved.astype(np.float32), "return_max": (solved > 0).astype(np.float32),
            "value_sum": np.zeros(k, np.float32), "pvl_sum": np.zeros(k, np.float32),
            "l1_sum": np.zeros(k, np.float32), "policy_version": np.zeros(k, np.int32)}


def play_actors(hub: str, names: list[str], batch: int, period_s: float, seconds: float, results: bool,
                out: Any) -> None:
    """One fleet process: an actor session per name, each asking for a level batch every `period_s` for
    `seconds` and, with `results`, publishing results for the batch's levels right after each answer; puts
    (answered latencies, unanswered count) on `out`."""
    from impulse.bus.levels import encode_level_results

    sessions = open_actor_sessions(hub, names)
    for session in sessions:
        session.wait_queryable(session.keys.levels_sample, 60)
    latencies: list[float] = []
    unanswered = 0
    lock = threading.Lock()
    stop_at = time.monotonic() + seconds

    def actor(session: Any) -> None:
        nonlocal unanswered
        rng = random.Random(session.ident)
        publisher = session.publisher(session.keys.levels_results(session.ident)) if results else None
        sent = 0
        next_at = time.monotonic() + random.uniform(0, period_s)
        while True:
            time.sleep(max(0.0, next_at - time.monotonic()))
            if time.monotonic() >= stop_at:
                return
            started = time.perf_counter()
            replies = session.get(session.keys.levels_sample, parameters=f"n={batch}", timeout_s=TIMEOUT_S)
            took = time.perf_counter() - started
            with lock:
                if replies:
                    latencies.append(took)
                else:
                    unanswered += 1
            if replies and publisher is not None:
                sent += 1
                publisher.put(encode_level_results(session.stamp, level_results(replies[0], rng), seq=sent))
            next_at += period_s

    run_each(sessions, actor)
    out.put((latencies, unanswered))


def latest_status(statuses: Any, keys: Any, newest: dict[str, Any]) -> dict[str, Any]:
    """`newest` updated with the curriculum service's status lines waiting in `statuses` (an inbox)."""
    from impulse.bus.status import read_status

    for received in statuses.poll():
        newest = read_status(received, keys).status
    return newest


def ahead_delta(before: dict[str, Any], after: dict[str, Any]) -> dict[str, Any]:
    """What the service did between two status lines: result messages applied, refused and dropped by a full
    inbox, the buffer's fill after; filtered batches of new levels made ahead, and batches drawn unfiltered because
    none was ready (those two only when levels are made ahead)."""
    done = {"results_applied": after.get("results", 0) - before.get("results", 0),
            "results_rejected": sum(after.get("rejected", {}).values()) - sum(before.get("rejected", {}).values()),
            "results_dropped_inbox_full": after.get("dropped_inbox_full", 0) - before.get("dropped_inbox_full", 0),
            "replayed_batches": after.get("count_replay_batches", 0) - before.get("count_replay_batches", 0),
            "new_batches": after.get("count_new_batches", 0) - before.get("count_new_batches", 0),
            "buffer_fill": after.get("buffer_fill")}
    if "levels_ahead" not in after:
        return done
    old, new = before.get("levels_ahead", {}), after["levels_ahead"]
    return {**done, "filtered_batches_made": new["made"] - old.get("made", 0),
            "unfiltered_batches": new["unfiltered"] - old.get("unfiltered", 0)}


def percentile_ms(latencies_ms: np.ndarray, q: float) -> float | None:
    """The q-th percentile of latencies in milliseconds, to 0.1 ms; None when there are none."""
    return round(float(np.percentile(latencies_ms, q)), 1) if latencies_ms.size else None


def measure(hub: str, service_pid: int, actors: int, processes: int, batch: int, period_s: float,
            seconds: float, results: bool) -> dict[str, Any]:
    got, memory = play_fleet(play_actors, lambda share: (hub, share, batch, period_s, seconds, results),
                             actors, processes, service_pid)
    latencies = np.asarray([lat for answered, _ in got for lat in answered]) * 1000
    unanswered = sum(missing for _, missing in got)
    return {
        "actors": actors,
        "fleet_processes": len(got),
        "period_s": period_s,
        "batch_levels": batch,
        "offered_per_s": round(actors / period_s, 1),
        "answered_per_s": round(latencies.size / seconds, 1),
        "unanswered": int(unanswered),
        "latency_p50_ms": percentile_ms(latencies, 50),
        "latency_p90_ms": percentile_ms(latencies, 90),
        "latency_p99_ms": percentile_ms(latencies, 99),
        "latency_max_ms": round(float(latencies.max()), 1) if latencies.size else None,
        "service_rss_mib_max": round(max(m["rss"] for m in memory), 1),
        "cpus": os.cpu_count(),
    }


def start_service(words: list[str], config: Path, hub: str, workdir: Path, overrides: list[str],
                  name: str) -> tuple[subprocess.Popen, Any]:
    """`impulse WORDS --config CONFIG` on the fleet's run in `workdir`, connected to `hub`, logging to
    `workdir/NAME.log`: (the process, its open log)."""
    log = (workdir / f"{name}.log").open("wb")
    process = subprocess.Popen(
        [sys.executable, "-m", "impulse.deploy.cli", *words, "--config", str(config), f"--connect={hub}",
         f"run_dir={workdir / 'run'}", f"name={RUN}", f"bus.hub={hub}", *overrides],
        cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    progress(f"{name} starting (log {workdir / f'{name}.log'}) ...")
    return process, log


def stop_service(process: subprocess.Popen, log: Any) -> None:
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=60)
    except subprocess.TimeoutExpired:
        process.kill()
    log.close()


def run_curriculum(config: Path, overrides: list[str], sizes: list[int], processes: int, period_s: float,
                   seconds: float, results: bool) -> int:
    from impulse.bus.config import BusConfig
    from impulse.bus.keys import OPERATOR
    from impulse.bus.session import Bus
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig

    overrides = ["env.levels=random", *overrides]
    batch = resolve_config(RunConfig, config, overrides).ppo.num_envs
    hub = f"tcp/127.0.0.1:{free_port()}"
    workdir = Path(tempfile.mkdtemp(prefix="fleet-"))
    with Bus(BusConfig(hub=hub), RUN, OPERATOR, "fleet-hub", listen=True) as bus:
        service, log = start_service(["curriculum", "serve"], config, hub, workdir, overrides, "curriculum")
        try:
            deadline = time.monotonic() + 600
            while not bus.wait_queryable(bus.keys.levels_sample, 5):
                if service.poll() is not None or time.monotonic() > deadline:
                    progress(f"the curriculum service never answered; see {workdir / 'curriculum.log'}")
                    return 1
            # The service declares its queryable before it compiles: the first answer waits for the compile.
            if not bus.get(bus.keys.levels_sample, parameters=f"n={batch}", timeout_s=600):
                progress(f"no first answer from the curriculum service; see {workdir / 'curriculum.log'}")
                return 1
            statuses = bus.inbox(bus.keys.status_pattern("curriculum"), 64, drop_oldest=True)
            status = latest_status(statuses, bus.keys, {})
            for actors in sizes:
                progress(f"{actors} actors, one request each every {period_s} s, for {seconds} s ...")
                row = measure(hub, service.pid, actors, processes, batch, period_s, seconds, results)
                time.sleep(1.5)  # the status line after the fleet stopped
                newer = latest_status(statuses, bus.keys, status)
                emit({**row, **ahead_delta(status, newer)})
                status = newer
        finally:
            stop_service(service, log)
    return 0


# -- the learner's half ---------------------------------------------------------------------------------------------

LEARNER_DEFAULTS = ("total_env_steps=1000000000000", "checkpoint.every_updates=1000000")
"""The learner runs for as long as the fleet does, and its checkpoints do not enter the measurement."""


def record_batch(config: Any) -> Any:
    """A trajectory batch of a real rollout with the config's agent (random initial weights) on random levels, as
    host arrays: what an actor of this run sends."""
    import jax

    from impulse.actors.rollout import rollout, start_rollout
    from impulse.actors.trajectory import make_batch
    from impulse.engine.env.spec import env_from_config
    from impulse.engine.levels.generator import sample_random_levels
    from impulse.learner.agent import make_agent

    spec, env_params = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    ppo = config.ppo
    levels = sample_random_levels(jax.random.PRNGKey(2), ppo.num_envs, spec.sizes)
    params = agent.init(jax.random.PRNGKey(0))
    carry = start_rollout(spec, env_params, levels, ppo.num_envs, jax.random.PRNGKey(1))
    play = jax.jit(lambda p, c: rollout(agent.act, p, spec, env_params, c, levels, ppo.num_steps))
    carry, steps, train_mask, episodes, _ = play(params, carry)
    return jax.device_get(make_batch(steps, carry.obs, 0, train_mask=train_mask, episodes=episodes))


class Sent(NamedTuple):
    """What one fleet process's actors did: frames sent, acknowledged, and sends skipped for want of credit;
    publish-to-acknowledgement latencies (s); credits outstanding, sampled at each send time."""

    sent: int
    acked: int
    skipped: int
    ack_latencies: list[float]
    outstanding: list[int]


def play_learner_actors(hub: str, names: list[str], batch: Any, sizes: Any, wire_settings: dict[str, bool],
                        credits: int, period_s: float, seconds: float, out: Any) -> None:
    """One fleet process: an actor per name, each following the learner's weights and sending `batch` every
    `period_s` while it holds a credit, for `seconds`; puts a `Sent` on `out`."""
    from impulse.actors.process import actor_index
    from impulse.actors.wire import TrajectoryWire
    from impulse.bus.codec import Rejected
    from impulse.bus.credits import decode_credit
    from impulse.bus.trajectories import encode_trajectory
    from impulse.bus.weights import decode_weights
    from impulse.engine.pytree import tree_arrays

    wire = TrajectoryWire(batch, sizes, **wire_settings)
    packed = wire.pack(tree_arrays(batch))
    sessions = open_actor_sessions(hub, names)
    lock = threading.Lock()
    totals = Sent(0, 0, 0, [], [])
    counts = {"sent": 0, "acked": 0, "skipped": 0}
    stop_at = time.monotonic() + seconds

    def actor(session: Any) -> None:
        keys = session.keys
        index = actor_index(session.ident)
        weights = session.inbox(keys.weights_policy, 1, drop_oldest=True, latest=True)
        acks = session.inbox(keys.credit(session.ident), 64, drop_oldest=True)
        frames = session.publisher(keys.traj(session.ident))
        incarnation = random.getrandbits(31)
        seq = acked = 0
        order = (-1, -1)
        sent_at: dict[int, float] = {}
        next_at = time.monotonic() + random.uniform(0, period_s)
        while time.monotonic() < stop_at:
            for received in weights.poll():
                try:
                    order = max(order, decode_weights(received.payload, keys.run).order)
                except Rejected:
                    continue
            for received in acks.poll():
                try:
                    credit = decode_credit(received.payload, keys.run)
                except Rejected:
                    continue
                if credit.incarnation == incarnation and acked < credit.acked_seq <= seq:
                    now = time.monotonic()
                    with lock:
                        totals.ack_latencies.extend(now - sent_at.pop(n) for n in range(acked + 1,
                                                                                       credit.acked_seq + 1))
                        counts["acked"] += credit.acked_seq - acked
                    acked = credit.acked_seq
            if order[0] >= 0 and time.monotonic() >= next_at:
                if seq - acked < credits:
                    seq += 1
                    epoch, version = order
                    session.stamp.acting_for(epoch, version)
                    arrays = {**packed, "behaviour_version": np.asarray(version, np.int32),
                              "seq": np.asarray(seq, np.int32), "actor_id": np.asarray(index, np.int32)}
                    sent_at[seq] = time.monotonic()
                    frames.put(encode_trajectory(session.stamp, arrays, seq=seq, incarnation=incarnation,
                                                 actor_index=index, layout=wire.format))
                    with lock:
                        counts["sent"] += 1
                        totals.outstanding.append(seq - acked)
                else:
                    with lock:
                        counts["skipped"] += 1
                next_at += period_s
            time.sleep(0.01)

    run_each(sessions, actor)
    out.put(totals._replace(**counts))


def learner_delta(before: dict[str, Any], after: dict[str, Any], seconds: float, steps_per_frame: int
                  ) -> dict[str, Any]:
    """What the learner's status lines say it did between `before` and `after`, `seconds` apart."""
    took, gave = before.get("ingested", {}), after.get("ingested", {})
    frames = gave.get("frames", 0) - took.get("frames", 0)
    busy = gave.get("seconds", 0.0) - took.get("seconds", 0.0)
    unpacked = gave.get("unpacked", 0) - took.get("unpacked", 0)
    unpacking = gave.get("unpack_seconds", 0.0) - took.get("unpack_seconds", 0.0)
    per_frame = (busy / frames if frames else 0.0) + (unpacking / unpacked if unpacked else 0.0)
    updates = after.get("update", 0) - before.get("update", 0)
    drops = {name: after.get(name, 0) - before.get(name, 0)
             for name in ("dropped_stale", "dropped_old_epoch", "dropped_overflow", "dropped_inbox_full", "lost")}
    rejected = {reason: count - before.get("rejected", {}).get(reason, 0)
                for reason, count in after.get("rejected", {}).items()}
    return {
        "learner_updates_per_s": round(updates / seconds, 2),
        "learner_steps_per_s": round(updates * steps_per_frame / seconds),
        "ingested_frames_per_s": round(frames / seconds, 1),
        "ingested_mb_per_s": round((gave.get("mb", 0.0) - took.get("mb", 0.0)) / seconds, 1),
        "receive_ms_per_frame": round(1000 * busy / frames, 2) if frames else None,
        "unpacked_frames_per_s": round(unpacked / seconds, 1),
        "unpack_ms_per_frame": round(1000 * unpacking / unpacked, 2) if unpacked else None,
        "ingest_share_of_learner_time": round((busy + unpacking) / seconds, 3),
        "ingest_capacity_steps_per_s": round(steps_per_frame / per_frame) if per_frame > 0 else None,
        "learner_queue": after.get("queue"),
        "drops": {name: count for name, count in drops.items() if count},
        "rejected": {reason: count for reason, count in rejected.items() if count},
    }


def measure_learner(hub: str, learner_pid: int, actors: int, processes: int, batch: Any, sizes: Any,
                    wire_settings: dict[str, bool], credits: int, period_s: float, seconds: float) -> dict[str, Any]:
    results, memory = play_fleet(
        play_learner_actors, lambda share: (hub, share, batch, sizes, wire_settings, credits, period_s, seconds),
        actors, processes, learner_pid)
    latencies = np.asarray([lat for got in results for lat in got.ack_latencies]) * 1000
    outstanding = np.asarray([n for got in results for n in got.outstanding])

    return {
        "actors": actors,
        "fleet_processes": len(results),
        "period_s": period_s,
        "credits": credits,
        "offered_frames_per_s": round(actors / period_s, 1),
        "sent_frames_per_s": round(sum(got.sent for got in results) / seconds, 1),
        "acked_frames_per_s": round(sum(got.acked for got in results) / seconds, 1),
        "skipped_no_credit": sum(got.skipped for got in results),
        "publish_to_ack_p50_ms": percentile_ms(latencies, 50),
        "publish_to_ack_p99_ms": percentile_ms(latencies, 99),
        "credits_outstanding_mean": round(float(outstanding.mean()), 2) if outstanding.size else None,
        **{f"learner_{part}_mib_max": round(max(m[part] for m in memory), 1)
           for part in ("rss", "private", "shared")},
        "cpus": os.cpu_count(),
    }


def run_learner(config_path: Path, overrides: list[str], sizes: list[int], processes: int, period_s: float,
                seconds: float, results: bool = False) -> int:
    """The learner's half (see the module docstring); `results` is the curriculum's option and unused here."""
    from impulse.bus.config import BusConfig
    from impulse.bus.keys import LEARNER, OPERATOR
    from impulse.bus.session import Bus
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig
    from impulse.engine.env.spec import env_from_config

    overrides = [*LEARNER_DEFAULTS, f"actors.num_actors={max(sizes)}", *overrides]
    config = resolve_config(RunConfig, config_path, overrides)
    progress("recording a trajectory batch from a real rollout ...")
    batch = record_batch(config)
    steps_per_frame = config.ppo.num_envs * config.ppo.num_steps
    wire_settings = {"compact": config.bus.wire_compact, "float16": config.bus.wire_float16}
    sizes_of_scene = env_from_config(config.env)[0].sizes
    hub = f"tcp/127.0.0.1:{free_port()}"
    workdir = Path(tempfile.mkdtemp(prefix="fleet-"))
    with Bus(BusConfig(hub=hub), RUN, OPERATOR, "fleet-hub", listen=True) as bus:
        statuses = bus.inbox(bus.keys.status_pattern(LEARNER), 64, drop_oldest=True)
        learner, log = start_service(["learner"], config_path, hub, workdir, overrides, "learner")
        try:
            deadline = time.monotonic() + 600
            status = latest_status(statuses, bus.keys, {})
            while not status:  # its first status line comes once the update is compiled
                if learner.poll() is not None or time.monotonic() > deadline:
                    progress(f"the learner never reported; see {workdir / 'learner.log'}")
                    return 1
                time.sleep(1.0)
                status = latest_status(statuses, bus.keys, {})
            for actors in sizes:
                progress(f"{actors} actors, one frame each every {period_s} s at most, for {seconds} s ...")
                started = time.monotonic()
                row = measure_learner(hub, learner.pid, actors, processes, batch, sizes_of_scene, wire_settings,
                                      config.actors.credits, period_s, seconds)
                newer = latest_status(statuses, bus.keys, status)
                frame = len(wire_bytes(batch, sizes_of_scene, wire_settings))
                emit({**row, "frame_mb": round(frame / 2**20, 2), "steps_per_frame": steps_per_frame,
                      **learner_delta(status, newer, time.monotonic() - started, steps_per_frame)})
                status = newer
                time.sleep(2.0)  # what is in flight drains before the next size
                status = latest_status(statuses, bus.keys, status)
        finally:
            stop_service(learner, log)
    return 0


def wire_bytes(batch: Any, sizes: Any, wire_settings: dict[str, bool]) -> bytes:
    """One frame of `batch` as an actor sends it."""
    from impulse.actors.wire import TrajectoryWire
    from impulse.bus.stamp import Stamp
    from impulse.bus.trajectories import encode_trajectory
    from impulse.engine.pytree import tree_arrays

    wire = TrajectoryWire(batch, sizes, **wire_settings)
    return bytes(encode_trajectory(Stamp(RUN), wire.pack(tree_arrays(batch)), seq=1, incarnation=1,
                                   actor_index=0, layout=wire.format))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench fleet", description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", choices=("curriculum", "learner"), default="curriculum",
                        help="the service the fleet drives")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 16, 64, 128, 256],
                        help="fleet sizes to measure, one after another")
    parser.add_argument("--processes", type=int, default=4, help="processes the fleet's sessions are spread over")
    parser.add_argument("--period", type=float, default=1.0,
                        help="seconds between an actor's level requests (curriculum) or frames (learner)")
    parser.add_argument("--seconds", type=float, default=30.0, help="measuring time per fleet size")
    parser.add_argument("--results", action="store_true",
                        help="curriculum: each actor also publishes made-up results for every batch it gets, so "
                             "the service scores levels, fills its buffer and replays")
    parser.add_argument("overrides", nargs="*", help="key=value overrides of the run config")
    args = parser.parse_args(argv)
    run = run_learner if args.against == "learner" else run_curriculum
    return run(args.config, args.overrides, args.actors, args.processes, args.period, args.seconds, args.results)


if __name__ == "__main__":
    raise SystemExit(main())
