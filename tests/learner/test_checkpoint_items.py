"""Checkpoints are separate items: each reader restores only what it needs, and foreign layouts fail clearly."""

from __future__ import annotations

import numpy as np
import orbax.checkpoint as ocp
import pytest

from impulse.learner.checkpoint import Checkpointer, CheckpointError

TRAIN = {"params": {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}, "version": np.array(4, np.int32)}
ENVS = {"positions": np.linspace(0, 1, 8, dtype=np.float32), "key": np.array([1, 2], np.uint32)}


def test_train_item_restores_alone_and_envs_on_request(tmp_path):
    with Checkpointer(tmp_path / "ck") as checkpoints:
        checkpoints.save(3, {"train": TRAIN, "envs": ENVS}, {"update": 3}, "name = 'x'\n", solve_rate=0.5)
    with Checkpointer(tmp_path / "ck") as checkpoints:
        items, counters, toml, step = checkpoints.restore({"train": TRAIN})
        assert set(items) == {"train"} and counters == {"update": 3} and toml == "name = 'x'\n" and step == 3
        np.testing.assert_array_equal(items["train"]["params"]["w"], TRAIN["params"]["w"])
        both = checkpoints.restore({"train": TRAIN, "envs": ENVS}, step=3)
        np.testing.assert_array_equal(both.items["envs"]["positions"], ENVS["positions"])


def test_a_train_only_checkpoint_has_no_envs_to_resume_from(tmp_path):
    with Checkpointer(tmp_path / "ck") as checkpoints:
        checkpoints.save(1, {"train": TRAIN}, {"update": 1}, "")
        with pytest.raises(CheckpointError, match="no envs item"):
            checkpoints.restore({"train": TRAIN, "envs": ENVS})
        with pytest.raises(ValueError, match="must be among"):
            checkpoints.save(2, {"state": ENVS}, {}, "")
        with pytest.raises(ValueError, match="must be among"):
            checkpoints.save(2, {}, {}, "")


def test_old_single_state_checkpoints_are_refused_with_a_reason(tmp_path):
    manager = ocp.CheckpointManager(tmp_path / "ck", options=ocp.CheckpointManagerOptions(create=True))
    manager.save(5, args=ocp.args.Composite(state=ocp.args.StandardSave(TRAIN), counters=ocp.args.JsonSave({})))
    manager.wait_until_finished()
    manager.close()
    with Checkpointer(tmp_path / "ck") as checkpoints:
        with pytest.raises(CheckpointError, match="older Impulse"):
            checkpoints.restore({"train": TRAIN})
