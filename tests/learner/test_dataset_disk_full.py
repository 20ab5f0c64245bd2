"""The recorder's dataset on a full disk (`learner.dataset`, through the writers' test hook): the shard the disk
refused leaves nothing in `.partial/`, the writer says so in one line naming the path and the space left, keeps
the episodes and writes them, each once, in the next shard once there is space; what its last flush cannot write
is counted as lost."""

from __future__ import annotations

import logging
import re
import time

import numpy as np
import pytest

from impulse.engine.io_errors import lift_write_limits, limit_writes
from impulse.learner import dataset
from impulse.learner.dataset import PARTIAL, DatasetWriter, Episode, folder_bytes, open_dataset

FREE = r"\(\d+(\.\d)? [KMGT]?i?B free of \d+(\.\d)? [KMGT]?i?B\)"


def episode(number: int) -> Episode:
    length = 10 + number % 3
    steps = {"obs/shapes": np.random.default_rng(number).normal(size=(length, 3)).astype(np.float32),
             "action": np.full((length, 2), number, np.int32), "reward": np.full(length, 0.5, np.float32)}
    return Episode(steps=steps, level_id=7, episode_return=0.5 * length, solved=True, policy_version=number,
                   actor=0, level=None)


@pytest.fixture(autouse=True)
def no_write_limits():
    yield
    lift_write_limits()


def test_a_shard_the_disk_refuses_is_kept_and_written_once_there_is_space(tmp_path, caplog,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(dataset, "RETRY_FULL_S", 0.3)
    path = tmp_path / "episodes"
    writer = DatasetWriter(path, {"size": "s"}, {}, max_bytes=10**9)
    writer.add([episode(0), episode(1)])
    writer.flush()
    limit_writes(tmp_path, folder_bytes(tmp_path) + 100)
    writer.add([episode(2), episode(3)])
    with caplog.at_level(logging.INFO, logger="impulse.learner.dataset"):
        assert writer.flush() is None
        assert writer.flush() is None, "not tried again before RETRY_FULL_S"
        assert not any((path / PARTIAL).iterdir()), "nothing of the refused shard is left"
        assert len(writer.pending) == 2 and writer.disk_full is not None
        writer.add([episode(4)])
        lift_write_limits()
        time.sleep(0.3)
        shard = writer.flush()
    assert shard is not None and writer.disk_full is None and writer.pending == []
    [error] = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert re.match(rf"^recording: no space left on device writing {re.escape(str(path / PARTIAL))}/\d+ {FREE}; "
                    "the episodes wait in memory", error), error
    assert "recording goes on" in caplog.text
    assert sorted(open_dataset(path).index().policy_version.tolist()) == [0, 1, 2, 3, 4], "each episode once"


def test_what_the_last_flush_cannot_write_is_counted_as_lost(tmp_path, caplog) -> None:
    writer = DatasetWriter(tmp_path / "episodes", {"size": "s"}, {}, max_bytes=10**9)
    limit_writes(tmp_path, folder_bytes(tmp_path) + 100)
    writer.add([episode(0), episode(1), episode(2)])
    with caplog.at_level(logging.INFO, logger="impulse.learner.dataset"):
        assert writer.flush(final=True) is None
    assert writer.counts["episodes_dropped_disk_full"] == 3 and writer.pending == []
    assert "the 3 episodes held are lost" in caplog.text
