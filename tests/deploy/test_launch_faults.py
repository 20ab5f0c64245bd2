"""A real distributed run (`impulse launch`: learner + 2 actor processes over Zenoh on loopback, CPU) that learns
our easy car while it is attacked on the open one-machine bus: malformed and foreign messages on every key, a
replayed old weights frame, a weights frame with a flipped bit, and a forged "finished" learner status. It must
keep training, the actors' policy versions must never go back, nobody may stop early, every refusal must reach
metrics.jsonl, and it must still reach an 80% solve rate. Its processes have monitoring on with no Rerun viewer
running: they count what they could not stream and neither stall nor keep it. Processes killed at random are
test_fault_injection.py's.

A recorder writes the run's episodes to a dataset meanwhile; it is killed with SIGKILL midway and restarted by the
launcher, and what it wrote stays whole: every episode's rewards add up to its recorded return, every level it
played is there, and the attacks' frames were refused. Behaviour cloning (`impulse train-bc`) of the solved
episodes then gives a policy that solves the easy car too."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
import pytest
from rerun.chunk import RrdReader

from impulse.actors.wire import trajectory_template
from impulse.bus.codec import Kind, decode, encode
from impulse.bus.keys import LEARNER, SCHEMA_MAJOR
from impulse.bus.weights import LEARNER_NONCE
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.engine.env.spec import env_from_config
from impulse.engine.pytree import tree_arrays
from impulse.learner.checkpoint import Checkpointer
from impulse.learner.dataset import open_dataset
from impulse.monitor.runs import SHARED_COLUMNS
from tests.support.launch_procs import (
    QUICK_LAUNCH,
    REPO,
    StatusWatcher,
    free_port,
    last_update,
    metrics,
    service_pids,
    start_launch,
    stop_launch,
    tail,
    wait_for,
)

pytestmark = pytest.mark.heavy

UPDATES = 32
"""The run's length: the easy car is solved after about 16 updates, and the attacks, which begin after update 3,
are over by about update 16 on a loaded 2-core machine (the malformed frames are checked only when the learner
takes them, behind the actors' frames)."""
EVERY = 4
STEPS_PER_UPDATE = 64 * 64


def zero_batch_arrays() -> dict[str, np.ndarray]:
    """A well-formed trajectory batch of the quick config, all zeros."""
    config = resolve_config(RunConfig, QUICK_LAUNCH)
    spec, _ = env_from_config(config.env)
    template = trajectory_template(spec, config.ppo.num_envs, config.ppo.num_steps)
    return tree_arrays(jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), template))


def malformed_trajectories(watcher: StatusWatcher) -> dict[str, Callable[[int, int], bytes]]:
    """One bad trajectory frame per reason the learner counts, by that reason, given the learner's policy version
    and a sequence number ("old_epoch" is accepted, then dropped because epoch 0 is no learner's; "duplicate" needs
    a number the stream has had). The learner unpacks and checks the arrays only of a frame it would train on, so
    those that fail the array checks say they were acted by its current policy."""
    run = watcher.run
    arrays = zero_batch_arrays()
    frame = lambda arrays, **kw: bytes(encode(Kind.TRAJECTORY, arrays, run=kw.pop("run", run),  # noqa: E731
                                              meta={"incarnation": 1}, **kw))
    good = frame(arrays, learner_epoch=0, seq=1)  # valid, but acted by weights of no learner epoch
    nan = dict(arrays, **{"steps/reward": np.full_like(arrays["steps/reward"], np.nan)})
    wrong_shape = dict(arrays, **{"steps/reward": np.zeros((3, 3), np.float32)})
    wrong_dtype = dict(arrays, **{"steps/reward": arrays["steps/reward"].astype(np.float64)})
    version = frame(arrays, seq=8, learner_epoch=1)
    return {
        "bad_magic": lambda v, n: b"XXXX" + good[4:],
        "truncated": lambda v, n: good[: len(good) // 2],
        "wrong_run": lambda v, n: frame(arrays, run="another-run", seq=n),
        "wrong_kind": lambda v, n: bytes(encode(Kind.WEIGHTS, arrays, run=run, meta={"incarnation": 1}, seq=n)),
        "non_finite": lambda v, n: frame(nan, seq=n, learner_epoch=1, policy_version=v),
        "bad_shape": lambda v, n: frame(wrong_shape, seq=n, learner_epoch=1, policy_version=v),
        "bad_dtype": lambda v, n: frame(wrong_dtype, seq=n, learner_epoch=1, policy_version=v),
        "bad_version": lambda v, n: bytes(version[:4]) + (SCHEMA_MAJOR + 1).to_bytes(2, "little") + bytes(version[6:]),
        "old_epoch": lambda v, n: frame(arrays, learner_epoch=0, seq=n),
        "duplicate": lambda v, n: good,
    }


CHECKED_WHEN_TAKEN = ("non_finite", "bad_shape", "bad_dtype")
"""Reasons found in a frame's arrays, which the learner checks only when it takes the frame for an update."""


class MalformedTrajectories:
    """Sends every bad trajectory frame until the learner's status counts its reason: the learner's inbox holds only
    a few frames between two updates and drops (and counts) the rest, so a frame it never read is sent again."""

    def __init__(self, watcher: StatusWatcher, frames: dict[str, Callable[[int, int], bytes]]) -> None:
        self.watcher = watcher
        self.frames = frames
        self.publisher = watcher.bus.publisher(watcher.bus.keys.traj("actor-9"))
        assert watcher.bus.wait_matching(self.publisher, 10), "the learner's trajectory subscription is not visible"
        self.publisher.put(np.random.default_rng(0).bytes(5000))
        self.sent_at = 0.0
        self.seq = 1

    def missing(self) -> set[str]:
        status = self.watcher.poll().get("learner", {})
        counted = set(status.get("rejected", {}))
        if status.get("dropped_old_epoch", 0) >= 1:
            counted.add("old_epoch")
        return set(self.frames) - counted

    def learner_version(self) -> int:
        """The learner's policy version now, from its answer to a weights query (its status line can be a few
        updates old, and anyone may broadcast weights on the open bus: this test does)."""
        bus = self.watcher.bus
        replies = bus.get(bus.keys.weights_latest, timeout_s=10)
        return decode(replies[0], run=self.watcher.run, kinds=Kind.WEIGHTS).policy_version if replies else 0

    def all_counted(self) -> bool:
        missing = self.missing()
        if missing and time.monotonic() - self.sent_at > 3.0:  # a status line comes every two seconds or so
            for reason in self.frames:  # in order: "old_epoch" before its "duplicate"
                if reason in missing:
                    self.seq += 1  # a new number: the learner takes a number once, whatever its arrays hold
                    version = self.learner_version() if reason in CHECKED_WHEN_TAKEN else 0
                    self.publisher.put(self.frames[reason](version, self.seq))
                    time.sleep(0.4)
            self.sent_at = time.monotonic()
        return not missing


def inject_foreign_weights_and_credit(watcher: StatusWatcher) -> None:
    """On the keys the actors listen to: weights of another network (in the learner's name), a stray frame of the
    right network far ahead of the learner from another learner instance (followers that adopted it would refuse
    every genuine frame after it as stale), and a garbage credit."""
    bus, run = watcher.bus, watcher.run
    [current] = bus.get(bus.keys.weights_latest, timeout_s=10)
    genuine = decode(current, run=run, kinds=Kind.WEIGHTS)
    weights = bus.publisher(bus.keys.weights_policy)
    assert bus.wait_matching(weights, 10)
    weights.put(bytes(encode(Kind.WEIGHTS, {"w": np.zeros(3, np.float32)}, run=run, policy_version=10**6,
                             learner_epoch=genuine.learner_epoch,
                             meta={"tree_hash": "another network", LEARNER_NONCE: genuine.meta[LEARNER_NONCE]})))
    weights.put(bytes(encode(Kind.WEIGHTS, dict(genuine.arrays), run=run, policy_version=10**6,
                             learner_epoch=genuine.learner_epoch,
                             meta={"tree_hash": genuine.meta["tree_hash"], LEARNER_NONCE: "stray"})))
    credit = bus.publisher(bus.keys.credit("actor-1"))
    assert bus.wait_matching(credit, 10)
    credit.put(np.random.default_rng(1).bytes(64))


def refused_by_both(versions: VersionWatch, reason: str) -> bool:
    return all(refusals(versions.poll().get(f"actor-{i}", {})).get(reason, 0) >= 1 for i in (0, 1))


def inject_replays_and_forgeries(watcher: StatusWatcher, versions: VersionWatch, old_weights: bytes,
                                 launch: subprocess.Popen, log: Path) -> None:
    """An old weights frame replayed, the current one with a flipped bit, and a forged "finished" learner status:
    anyone on the open bus can publish on any key. Each weights frame is sent again, once a second, until both
    actors have refused it (each frame an actor's inbox holds is checked, and those it had to drop are counted as
    overwritten, so a resend is only needed when a frame was overwritten)."""
    bus = watcher.bus
    [current] = bus.get(bus.keys.weights_latest, timeout_s=10)
    flipped = bytearray(current)
    flipped[len(flipped) - 100] ^= 0x01  # inside the last array's bytes
    weights = bus.publisher(bus.keys.weights_policy)
    assert bus.wait_matching(weights, 10)
    for frame, reason, what in ((old_weights, "stale", "the replayed weights"),
                                (bytes(flipped), "digest", "the weights with a flipped bit")):
        sent_at = [0.0]

        def refused(frame: bytes = frame, reason: str = reason, sent_at: list[float] = sent_at) -> bool:
            if time.monotonic() - sent_at[0] >= 1.0:
                weights.put(frame)
                sent_at[0] = time.monotonic()
            return refused_by_both(versions, reason)

        wait_for(refused, 60, f"both actors to refuse {what}", launch, log)
    status = bus.publisher(bus.keys.status(LEARNER, "learner"))
    assert bus.wait_matching(status, 10)
    status.put(bytes(encode(Kind.METRICS, {}, run=watcher.run, meta={"name": "learner", "finished": True})))


class VersionWatch:
    """The actors' policy versions as their status lines report them; fails if one ever goes back."""

    def __init__(self, watcher: StatusWatcher) -> None:
        self.watcher = watcher
        self.highest: dict[str, int] = {}

    def poll(self) -> dict[str, dict]:
        statuses = self.watcher.poll()
        for name, status in statuses.items():
            if name.startswith("actor-") and status.get("policy_version", -1) >= 0:
                version = status["policy_version"]
                assert version >= self.highest.get(name, -1), f"{name} went back to version {version}"
                self.highest[name] = version
        return statuses


def refusals(status: dict) -> dict[str, int]:
    return status.get("rejected", {}) if isinstance(status.get("rejected"), dict) else {}


def test_launch_learns_through_bad_messages_and_killed_processes(tmp_path):
    run_dir = tmp_path / "faults"
    port = free_port()
    # Monitoring on with no viewer running: the processes must neither stall nor keep what they cannot send.
    launch, log = start_launch(run_dir, port, f"total_env_steps={UPDATES * STEPS_PER_UPDATE}",
                               f"checkpoint.every_updates={EVERY}", "monitor.enabled=true",
                               f"monitor.url=rerun+http://127.0.0.1:{free_port()}/proxy",
                               "recorder.path={run_dir}/dataset", "recorder.flush_s=2")
    watcher = StatusWatcher(run_dir.name, port)
    versions = VersionWatch(watcher)
    try:
        # Made while the processes start (it traces the rollout's batch template), so the attacks begin at once.
        frames = malformed_trajectories(watcher)
        wait_for(lambda: last_update(run_dir) >= 3, 400, "the first updates", launch, log)
        [old_weights] = watcher.bus.get(watcher.bus.keys.weights_latest, timeout_s=10)
        old_version = decode(old_weights, run=watcher.run, kinds=Kind.WEIGHTS).policy_version

        # Malformed and foreign messages: dropped and counted, training goes on.
        malformed = MalformedTrajectories(watcher, frames)
        inject_foreign_weights_and_credit(watcher)
        wait_for(malformed.all_counted, 60, "the learner to count every bad trajectory by its reason", launch, log)
        wait_for(lambda: (malformed.publisher.put(frames["bad_shape"](0, 1)), time.sleep(0.5),
                          refusals(watcher.poll().get("recorder", {})).get("bad_shape", 0) >= 1)[-1], 30,
                 "the recorder to refuse bad trajectories too", launch, log)

        # A flood of frames overflows the learner's trajectory inbox: the frames it cannot hold are counted.
        flood = watcher.bus.publisher(watcher.bus.keys.traj("actor-8"))
        garbage = np.random.default_rng(2).bytes(200)
        wait_for(lambda: ([flood.put(garbage) for _ in range(50)],
                          watcher.poll().get("learner", {}).get("dropped_inbox_full", 0) >= 1)[1], 30,
                 "the learner to count frames its full inbox dropped", launch, log)
        streams = {i: watcher.poll()[f"actor-{i}"]["monitor"] for i in (0, 1)}
        assert all(not s["viewer"] and s["frames_logged"] == 0 and s["no_viewer"] >= 1 for s in streams.values()), (
            streams)
        wait_for(lambda: all(refusals(versions.poll().get(f"actor-{i}", {})).get(reason, 0) >= 1
                             for i in (0, 1) for reason in ("tree_hash", "foreign_learner")), 30,
                 "both actors to count the foreign and the stray weights", launch, log)
        assert refusals(watcher.poll()["actor-1"]).get("bad_magic", 0) >= 1, "actor-1 counts the garbage credit"

        # A replay of old weights and a corrupted copy of the newest are refused; the versions never go back; a
        # forged "finished" stops nobody while the learner is there.
        wait_for(lambda: all(versions.poll().get(f"actor-{i}", {}).get("policy_version", -1) > old_version
                             for i in (0, 1)), 60, "both actors past the captured weights", launch, log)
        inject_replays_and_forgeries(watcher, versions, old_weights, launch, log)
        after_injection = last_update(run_dir)
        wait_for(lambda: (versions.poll(), last_update(run_dir) >= after_injection + 2)[1], 60,
                 "training to go on", launch, log)
        assert "ended" not in log.read_text(), "an actor stopped on the forged status"

        # The recorder killed with SIGKILL once it has written shards: the launcher starts it again.
        wait_for(lambda: any((run_dir / "dataset" / "shards").glob("0*")), 60, "the recorder's first shard", launch,
                 log)
        [recorder] = service_pids(run_dir, "recorder")
        os.kill(recorder, signal.SIGKILL)
        recorder_log = run_dir / "logs" / "recorder.log"
        wait_for(lambda: recorder_log.read_text().count("recorder up:") == 2, 60, "the recorder's restart", launch,
                 log)

        assert launch.wait(timeout=600) == 0, tail(log)
    finally:
        watcher.close()
        stop_launch(launch, run_dir)

    for index in (0, 1):  # told by the learner's last status, as actors on other hosts are
        assert f"the learner finished the run: actor-{index} stops" in (run_dir / "logs" / f"actor-{index}.log"
                                                                         ).read_text()
    # Each process checked its program against its share of the host's memory: the learner and two actors.
    for name, what in (("learner", "the learner's update"), ("actor-0", "actor-0's rollout")):
        text = (run_dir / "logs" / f"{name}.log").read_text()
        assert re.search(rf"{what} needs [\d.]+ GiB of the [\d.]+ GiB free \(its 1/3 share: 3 processes", text), name
    # Every refusal reached metrics.jsonl (the learner's own and, from their status lines, the actors'), and every
    # update has one row.
    rows = metrics(run_dir)
    assert [row["update"] for row in rows] == list(range(1, UPDATES + 1))
    # The columns both modes write (tests/learner/test_learns.py checks a fused run's rows).
    assert {row["update"]: sorted(set(SHARED_COLUMNS) - row.keys()) for row in rows
            if not set(SHARED_COLUMNS) <= row.keys()} == {}
    last = rows[-1]
    assert all(last.get(f"rejected/{reason}", 0) >= 1 for reason in set(malformed.frames) - {"old_epoch"}), last
    assert last["drops/dropped_old_epoch"] >= 1 and "drops/dropped_inbox_full" in last, last
    assert last.get("rejected/actor/stale", 0) >= 2 and last.get("rejected/actor/digest", 0) >= 2, last
    assert last.get("rejected/actor/foreign_learner", 0) >= 2, last
    assert last.get("rejected/recorder/bad_shape", 0) >= 1, last  # the recorder's refusals reach the rows too
    assert max(versions.highest.values()) <= UPDATES, versions.highest  # the stray frame was never adopted
    scores = json.loads((run_dir / "eval.json").read_text())
    assert scores["s_easy_car_right"]["solve_rate"] >= 0.8, scores
    config = resolve_config(RunConfig, run_dir / "config.toml")
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        assert checkpoints.latest_step() == UPDATES
    # `impulse eval` reads the learner's train-only checkpoint; --record draws one episode per level to an .rrd.
    recorded = tmp_path / "eval.rrd"
    evaluated = subprocess.run([sys.executable, "-m", "impulse.deploy.cli", "eval", "--checkpoint", str(run_dir),
                                "--attempts", "4", "--record", str(recorded)], capture_output=True, text=True,
                               timeout=300, env={**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache")})
    assert evaluated.returncode == 0 and "s_easy_car_right" in evaluated.stdout, evaluated.stderr
    check_eval_recording(recorded, scores)
    check_dataset_and_clone_it(run_dir, tmp_path)


def check_dataset_and_clone_it(run_dir: Path, tmp_path: Path) -> None:
    """The recorder's dataset after its kill: whole, with its levels, written by both incarnations; then a policy
    cloned from its solved episodes solves the level."""
    recorder_log = (run_dir / "logs" / "recorder.log").read_text()
    assert recorder_log.count("recorder up:") == 2, tail(run_dir / "logs" / "recorder.log")
    assert "recorder done:" in recorder_log.rsplit("recorder up:", 1)[1]  # the second stopped cleanly
    dataset = open_dataset(run_dir / "dataset")
    index = dataset.index()
    steps = dataset.steps()
    starts = np.concatenate([[0], np.cumsum(index.length)[:-1]])
    np.testing.assert_allclose(np.add.reduceat(steps["reward"], starts), index.episode_return, atol=1e-4)
    assert index.has_level.all() and set(dataset.levels()) == set(index.level_id.tolist())
    assert set(index.actor.tolist()) == {0, 1}
    assert index.episodes >= 100 and index.solved.sum() >= 50, (index.episodes, index.solved.sum())
    assert not any((run_dir / "dataset" / ".partial").glob("*"))

    cloned = tmp_path / "cloned"
    result = subprocess.run([sys.executable, "-m", "impulse.deploy.cli", "train-bc", "--dataset",
                             str(run_dir / "dataset"), f"run_dir={cloned}", "bc.epochs=10", "bc.batch_size=256"],
                            capture_output=True, text=True, timeout=300,
                            env={**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache")})
    assert result.returncode == 0, result.stderr[-3000:]
    rows = [json.loads(line) for line in (cloned / "metrics.jsonl").read_text().splitlines()]
    assert [row["epoch"] for row in rows] == list(range(1, 11))
    # Better than a uniform policy over the 6 multi-discrete dimensions (3, 3, 3, 3, 2, 2 choices) on episodes it
    # never trained on. (The first epoch already reaches the plateau, so epoch 1 against epoch 10 is noise.)
    uniform = 4 * math.log(3) + 2 * math.log(2)
    assert all(row["bc/held_out_loss"] < uniform - 0.05 for row in rows[1:]), (uniform, rows)
    clone_scores = json.loads((cloned / "eval.json").read_text())
    assert clone_scores["s_easy_car_right"]["solve_rate"] >= 0.8, clone_scores


def check_eval_recording(path, scores: dict) -> None:
    """One episode per evaluated level, each drawn frame by frame and ended by one outcome line."""
    rows: dict[str, int] = {}
    outcomes: dict[str, list[str]] = {}
    for chunk in RrdReader(path).stream().collect().stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        if chunk.entity_path.endswith("/episodes"):
            lines = [t for row in chunk.to_record_batch().column("TextLog:text").to_pylist() for t in row]
            outcomes.setdefault(chunk.entity_path, []).extend(lines)
    for level in scores:
        entity = f"/rollouts/eval/{level}"
        assert rows.get(f"{entity}/scene/polygons", 0) >= 2, (level, sorted(rows))
        assert rows[f"{entity}/scene/polygons"] == rows[f"{entity}/reward"]
        [outcome] = outcomes.get(f"{entity}/episodes", [None])
        assert outcome is not None and outcome.startswith("episode 0 "), (level, outcome)
