"""The recorded dataset (`learner.dataset`): whole episodes and their levels round-trip with their index, disk use
stays bounded, a writer killed at random moments (kill -9) leaves only whole shards and a restarted one goes on
after them; the recorder's episode assembly (`learner.recorder.EpisodeAssembler`) keeps exactly the episodes it
saw whole, and an episode whose level it has not heard yet waits for it (`learner.recorder.LevelWait`)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zarr

from impulse.actors.trajectory import EpisodeStats, Trajectory, TrajectoryBatch
from impulse.engine.levels.level import level_id_words
from impulse.learner.dataset import DatasetError, DatasetWriter, Episode, folder_bytes, open_dataset
from impulse.learner.recorder import EpisodeAssembler, LevelWait
from tests.support.paths import REPO

ENV = {"size": "s", "observation": "entity", "levels": ["a", "b"]}
NETWORK = {"kind": "entity", "width": 8}


def episode(number: int, with_level: bool = True, width: int = 2) -> Episode:
    """Episode `number`: its length, observations (random, so that they do not compress), actions and rewards all
    follow from the number, so a reader can check every step; its policy version is the number."""
    length = 20 + number % 7
    steps = {
        "obs/shapes": np.random.default_rng(number).normal(size=(length, 3, width)).astype(np.float32),
        "obs/mask": np.arange(length)[:, None] % 2 == np.arange(3)[None, :] % 2,
        "action": np.full((length, 6), number % 3, np.int32),
        "reward": np.full(length, 0.5, np.float32),
    }
    level = {"level_id": level_id_words(1000 + number % 3), "scene/position": np.full((4, 2), number % 3, np.float32)}
    return Episode(steps=steps, level_id=1000 + number % 3, episode_return=0.5 * length, solved=number % 2 == 0,
                   policy_version=number, actor=number % 2, level=level if with_level else None)


def check_episodes(path, width: int = 2) -> np.ndarray:
    """Every episode of the dataset at `path` against `episode(number, width=width)`; returns the numbers found."""
    dataset = open_dataset(path)
    index = dataset.index()
    steps = dataset.steps()
    offset = 0
    for row in range(index.episodes):
        expected = episode(int(index.policy_version[row]), width=width)
        length = int(index.length[row])
        assert length == expected.length
        for name, array in expected.steps.items():
            np.testing.assert_array_equal(steps[name][offset:offset + length], array, err_msg=name)
        assert index.episode_return[row] == expected.episode_return and index.solved[row] == expected.solved
        offset += length
    assert offset == index.steps == (steps["reward"].shape[0] if steps else 0)
    return index.policy_version


def test_episodes_round_trip_with_their_index_and_levels(tmp_path):
    path = tmp_path / "data"
    writer = DatasetWriter(path, ENV, NETWORK, max_bytes=10**9)
    writer.add([episode(0), episode(1, with_level=False), episode(2)])
    first = writer.flush()
    writer.add([episode(3)])
    assert writer.flush() is not None and writer.flush() is None  # nothing waiting: no empty shard
    assert first.name == "00000000" and writer.counts["shards_written"] == 2
    assert writer.bytes_used == folder_bytes(path)

    dataset = open_dataset(path)
    assert dataset.env == ENV and dataset.network == NETWORK
    index = dataset.index()
    assert list(index.shard) == [0, 0, 0, 1] and list(index.start) == [0, 20, 41, 0]
    assert list(index.has_level) == [True, False, True, True] and list(index.actor) == [0, 1, 0, 1]
    assert list(index.level_id) == [1000, 1001, 1002, 1000]
    np.testing.assert_array_equal(check_episodes(path), [0, 1, 2, 3])
    only_solved = dataset.steps(index.solved)
    assert only_solved["reward"].shape[0] == index.length[index.solved].sum()
    np.testing.assert_array_equal(only_solved["action"][:, 0],
                                  np.repeat(index.policy_version[index.solved] % 3, index.length[index.solved]))
    levels = dataset.levels()
    assert sorted(levels) == [1000, 1002]  # episode 1's level was never heard
    np.testing.assert_array_equal(levels[1002]["scene/position"], np.full((4, 2), 2, np.float32))
    # The dataset is plain zarr: any zarr reader opens it.
    assert zarr.open_group(path, mode="r")["shards/00000001/steps/action"].shape == (23, 6)

    again = DatasetWriter(path, ENV, NETWORK, max_bytes=10**9)  # appending goes on after the last shard
    assert again.next_shard == 2
    with pytest.raises(DatasetError, match="recorded with env"):
        DatasetWriter(path, {**ENV, "size": "m"}, NETWORK, max_bytes=10**9)
    with pytest.raises(DatasetError, match="no such folder"):
        open_dataset(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="not a zarr group"):
        open_dataset(tmp_path / "empty")
    zarr.open_group(tmp_path / "other", mode="w").attrs["format"] = "something else"
    with pytest.raises(DatasetError, match="not an Impulse episode dataset"):
        open_dataset(tmp_path / "other")


def test_disk_use_is_bounded_by_stopping_or_by_dropping_the_oldest_shards(tmp_path):
    wide = lambda number: episode(number, width=256)  # noqa: E731  (data, not metadata, fills the disk)
    probe = DatasetWriter(tmp_path / "probe", ENV, NETWORK, max_bytes=10**9)
    probe.add([wide(n) for n in range(4)])
    shard = folder_bytes(probe.flush())
    limit = int(folder_bytes(tmp_path / "probe") - shard + 2.5 * shard)  # room for two shards of four episodes

    stop = DatasetWriter(tmp_path / "stop", ENV, NETWORK, max_bytes=limit)
    for number in range(0, 20, 4):
        stop.add([wide(n) for n in range(number, number + 4)])
        stop.flush()
    assert stop.full and stop.counts["shards_written"] == 2
    assert stop.counts["episodes_dropped_full"] == 12 and folder_bytes(tmp_path / "stop") <= limit
    stop.add([wide(99)])
    assert stop.pending == [] and stop.counts["episodes_dropped_full"] == 13

    ring = DatasetWriter(tmp_path / "ring", ENV, NETWORK, max_bytes=limit, when_full="drop_oldest")
    for number in range(0, 20, 4):
        ring.add([wide(n) for n in range(number, number + 4)])
        ring.flush()
        assert folder_bytes(tmp_path / "ring") <= limit
    assert not ring.full and ring.counts["shards_written"] == 5 and ring.counts["shards_dropped"] == 3
    np.testing.assert_array_equal(check_episodes(tmp_path / "ring", width=256), range(12, 20))  # the newest two


WRITER = """
import sys
from impulse.learner.dataset import DatasetWriter, open_dataset
from tests.learner.test_dataset import ENV, NETWORK, episode

path = sys.argv[1]
writer = DatasetWriter(path, ENV, NETWORK, max_bytes=10**10)
index = open_dataset(path).index()
number = int(index.policy_version.max()) + 1 if index.episodes else 0
print("ready", flush=True)
while True:
    writer.add([episode(n) for n in range(number, number + 400)])
    writer.flush()
    number += 400
"""


@pytest.mark.heavy  # starts processes of its own
def test_a_writer_killed_at_random_moments_leaves_only_whole_shards(tmp_path):
    path = tmp_path / "data"
    rng = np.random.default_rng(0)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    killed_mid_write = 0
    for attempt in range(6):
        writer = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, env=env,
                                  cwd=REPO)
        assert writer.stdout.readline().strip() == b"ready"
        deadline = time.monotonic() + 60
        if attempt % 2:  # at a random moment after it has written a shard
            before = len(list((path / "shards").glob("0*")))
            while len(list((path / "shards").glob("0*"))) == before and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(rng.uniform(0, 0.5))
        else:  # while a shard is being written
            while not any((path / ".partial").glob("*")) and time.monotonic() < deadline:
                time.sleep(0.001)
            time.sleep(rng.uniform(0, 0.02))
        writer.send_signal(signal.SIGKILL)
        writer.wait(timeout=30)
        killed_mid_write += any((path / ".partial").glob("*"))
        numbers = check_episodes(path)
        # Shards are numbered 0, 1, 2, ... and each holds 400 episodes in order.
        shards = sorted(entry.name for entry in (path / "shards").iterdir() if entry.is_dir())
        assert shards == [f"{n:08d}" for n in range(len(shards))]
        np.testing.assert_array_equal(numbers, np.arange(400 * len(shards)))
    assert len(shards) >= 3, "the writers wrote fewer shards than they were given time for"
    assert killed_mid_write >= 1, "no kill landed while a shard was being written"
    DatasetWriter(path, ENV, NETWORK, max_bytes=10**10)  # a restart removes what the last one left unfinished
    assert not any((path / ".partial").glob("*"))


def batch(done: list[list[bool]], returns: float = 1.0, version: int = 3) -> TrajectoryBatch:
    """A [T, E] batch whose rewards are 1 on every step; observation = the step's position in time."""
    done_arr = np.asarray(done, bool)
    steps, envs = done_arr.shape
    zeros = np.zeros((steps, envs), np.float32)
    trajectory = Trajectory(
        obs=np.broadcast_to(np.arange(steps, dtype=np.float32)[:, None, None], (steps, envs, 2)).copy(),
        action=np.zeros((steps, envs, 6), np.int32), log_prob=zeros, value=zeros,
        reward=np.ones((steps, envs), np.float32), done=done_arr, solved=done_arr.copy(),
        truncated=np.zeros_like(done_arr), episode_return=np.where(done_arr, returns, 0.0).astype(np.float32),
        level_id=np.broadcast_to(level_id_words(77), (steps, envs, 2)).copy())
    return TrajectoryBatch(trajectory, np.zeros((envs, 2), np.float32), np.int32(version),
                           np.ones((steps, envs), bool), np.int32(1), np.int32(0),
                           EpisodeStats(*(np.zeros((), np.int32) for _ in EpisodeStats._fields)))


def test_the_recorder_keeps_exactly_the_episodes_it_saw_whole():
    assembler = EpisodeAssembler()
    t, f = True, False
    # An actor's first batch (seq 1) starts every episode: env 0 ends one at step 2, env 1 none yet.
    first = assembler.add("actor-0", 5, 1, batch([[f, f], [f, f], [t, f], [f, f]]))
    assert [(len(steps["reward"]), facts["level_id"], facts["policy_version"], facts["actor"])
            for steps, facts in first] == [(3, 77, 3, 1)]
    # The next batch completes env 1's 6-step episode (4 + 2) and env 0's second (1 + 3).
    second = assembler.add("actor-0", 5, 2, batch([[f, f], [f, t], [t, f], [f, f]]))
    assert sorted(len(steps["reward"]) for steps, _ in second) == [4, 6]
    six = next(steps for steps, _ in second if len(steps["reward"]) == 6)
    np.testing.assert_array_equal(six["obs"][:, 0], [0, 1, 2, 3, 0, 1])  # stitched across the two batches
    # A lost batch (seq 4 after 2): the episodes under way cannot be whole; the next ends are cut, then whole again.
    third = assembler.add("actor-0", 5, 4, batch([[t, f], [f, f], [f, t], [t, f]], returns=9.0))
    assert [len(steps["reward"]) for steps, _ in third] == [3]
    assert assembler.counts["batches_lost"] == 1 and assembler.counts["episodes_cut"] == 4
    # A recorder that joins a stream midway (seq 7 of another actor) keeps nothing until the episodes restart.
    assert assembler.add("actor-1", 9, 7, batch([[t, t], [f, f]])) == []
    # A restarted actor (new incarnation): its predecessor's episodes under way are cut.
    cut_before = assembler.counts["episodes_cut"]
    assert len(assembler.add("actor-0", 6, 1, batch([[t, t]]))) == 2
    assert assembler.counts["episodes_cut"] == cut_before + 1
    assert assembler.counts["episodes_whole"] == 6


def test_an_episode_waits_for_its_level_until_the_wait_is_over():
    wait = LevelWait(wait_s=15.0)
    for number, now in ((0, 100.0), (1, 101.0), (2, 102.0)):  # levels 1000, 1001 and 1002, none heard yet
        wait.hold(episode(number, with_level=False), now)
    heard = {1001: episode(1).level}
    [late] = wait.settle(heard, now=105.0, final=False)  # heard late: it goes with its level
    assert late.policy_version == 1 and late.level is heard[1001]
    settled = wait.settle(heard, now=105.0, final=False)
    assert settled == [] and len(wait) == 2  # the other two still wait
    [gone] = wait.settle(heard, now=115.0, final=False)  # episode 0's 15 s are over: written without its level
    assert (gone.policy_version, gone.level) == (0, None) and len(wait) == 1
    [last] = wait.settle({}, now=116.0, final=True)  # the recorder's last flush takes the rest as they are
    assert (last.policy_version, last.level, len(wait)) == (2, None, 0)
