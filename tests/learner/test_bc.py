"""Behaviour cloning (`learner.bc`): the episode selection and split, a dataset whose observations another
network reads refused by name, and cloning that learns: on the transitions Kinetix's own code wrote in its offline
format (tests/fixtures/kinetix/offline), a flat policy comes to choose the recorded actions. The end-to-end case,
a recorded run cloned into a policy that solves its level, is tests/deploy/test_launch_faults.py's."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import pytest

from impulse.engine.env.config import EnvConfig
from impulse.engine.env.spec import env_from_config
from impulse.learner.agent import make_agent
from impulse.learner.bc import clone, cloning_data, is_kinetix_dataset, kinetix_cloning_data, select_episodes
from impulse.learner.config import BCConfig, NetworkConfig
from impulse.learner.dataset import DatasetError, DatasetWriter, open_dataset
from tests.learner.test_dataset import ENV, NETWORK, episode

KINETIX = Path(__file__).resolve().parents[1] / "fixtures" / "kinetix" / "offline" / "flat"


def test_selection_keeps_solved_episodes_above_the_return_and_holds_some_out(tmp_path):
    writer = DatasetWriter(tmp_path / "data", ENV, NETWORK, max_bytes=10**9)
    writer.add([episode(n) for n in range(40)])
    writer.flush()
    index = open_dataset(tmp_path / "data").index()
    train, held = select_episodes(index, BCConfig(validation_fraction=0.25), seed=0)
    assert not (train & held).any() and ((train | held) == index.solved).all() and held.sum() == 5
    again, _ = select_episodes(index, BCConfig(validation_fraction=0.25), seed=0)
    assert (again == train).all()  # the seed decides the split
    train, held = select_episodes(index, BCConfig(solved_only=False, min_return=12.0, validation_fraction=0),
                                  seed=0)
    assert (train == (index.episode_return >= 12.0)).all() and not held.any()


def test_observations_another_network_reads_are_refused_by_name(tmp_path):
    writer = DatasetWriter(tmp_path / "data", ENV, NETWORK, max_bytes=10**9)
    writer.add([episode(0)])
    writer.flush()
    dataset = open_dataset(tmp_path / "data")
    spec, _ = env_from_config(EnvConfig(observation="symbolic"))
    agent = make_agent(NetworkConfig(kind="flat", width=16, depth=1), spec)
    with pytest.raises(DatasetError, match="do not fit this network's environment: obs: the dataset has nothing"):
        cloning_data(dataset, np.ones(1, bool), agent)


@pytest.mark.skipif(not KINETIX.is_dir(), reason=f"Kinetix offline fixture not found at {KINETIX}")
def test_cloning_learns_the_actions_of_a_kinetix_dataset():
    assert is_kinetix_dataset(KINETIX) and not is_kinetix_dataset(KINETIX.parent)
    spec, _ = env_from_config(EnvConfig(size="s", observation="symbolic"))
    agent = make_agent(NetworkConfig(kind="flat", width=64, depth=2), spec)
    train, held_out = kinetix_cloning_data(KINETIX, agent, validation_fraction=0.25, seed=0)
    assert (train.steps, held_out.steps) == (36, 12)
    assert jax.tree.leaves(train.obs)[0].shape[0] == 36 and train.action.shape == (36, 6)
    epochs = []
    clone(agent, agent.init(jax.random.PRNGKey(0)), train, held_out,
          BCConfig(epochs=300, batch_size=12, learning_rate=3e-3), seed=0, on_epoch=epochs.append)
    assert [e.epoch for e in epochs] == list(range(1, 301))
    # Random actions cannot be predicted from held-out states, but the training steps can be learnt by heart.
    assert epochs[-1].loss < 0.5 * epochs[0].loss, (epochs[0], epochs[-1])
    assert np.isfinite(epochs[-1].held_out_loss) and 0 <= epochs[-1].held_out_agreement <= 1
