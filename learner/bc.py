"""Behaviour cloning: a policy learns to take the actions of a recorded dataset (`learner.dataset`), by maximum
likelihood of the recorded action under the policy's action distribution, the loss Kinetix's behaviour-cloning
baseline uses too.

1. `select_episodes`: which episodes to learn from (those that ended solved, those with at least some return);
   a fraction of them, drawn by the seed, is held out to measure the loss on episodes not trained on.
2. `cloning_data`: their steps as the network's observations and actions, on the device. A dataset in Kinetix's
   offline format (`learner.kinetix_offline`) gives its transitions instead (`kinetix_cloning_data`): it
   holds states rather than observations, so our observation of each state is computed, and it has no episode
   outcomes to select by.
3. `clone`: epochs of shuffled minibatches of the negative log-likelihood, one compiled program per epoch.

The critic is left as initialised: the cloned policy is a starting point for evaluation and for fine-tuning with
PPO (`impulse train --init-from`), which trains the value head first thing.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from impulse.engine.env.observations import observation_shape, observe
from impulse.engine.pytree import path_name, tree_from_arrays
from impulse.learner.agent import Agent
from impulse.learner.config import BCConfig
from impulse.learner.dataset import Dataset, DatasetError, EpisodeIndex
from impulse.learner.kinetix_offline import kinetix_offline_observations, read_kinetix_offline

Array = jax.Array
log = logging.getLogger("impulse.bc")


class CloningData(NamedTuple):
    """Steps to learn from: the observations (the network's pytree, leaves [N, ...]) and the actions [N, ...]."""

    obs: Any
    action: Array

    @property
    def steps(self) -> int:
        return int(self.action.shape[0])


class EpochStats(NamedTuple):
    """One epoch of cloning: mean loss on the training steps, and loss and action agreement (the policy's most
    likely action equals the recorded one in every dimension) on the held-out steps (NaN without any)."""

    epoch: int
    loss: float
    held_out_loss: float
    held_out_agreement: float
    seconds: float


def select_episodes(index: EpisodeIndex, config: BCConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, held out) masks over the dataset's episodes: those `config` selects (solved only, minimum return),
    split at random by `seed` with `config.validation_fraction` held out."""
    chosen = index.episode_return >= config.min_return
    if config.solved_only:
        chosen &= index.solved
    rows = np.flatnonzero(chosen)
    rng = np.random.default_rng(seed)
    held = rng.permutation(rows)[: int(round(len(rows) * config.validation_fraction))]
    held_out = np.zeros(index.episodes, bool)
    held_out[held] = True
    return chosen & ~held_out, held_out


def cloning_data(dataset: Dataset, selected: np.ndarray, agent: Agent) -> CloningData:
    """The steps of the `selected` episodes as the agent's observations and actions, on the device; the
    dataset's observations must be the ones the agent's network reads (`DatasetError` says which differ)."""
    steps = dataset.steps(selected)
    if not steps:
        return CloningData(None, jnp.zeros((0,), jnp.int32))
    template = {"obs": observation_shape(agent.spec)}
    obs_arrays = {name: array for name, array in steps.items() if name.startswith("obs")}
    wanted = _named_shapes(template)  # "obs/..." as the dataset names them ("obs" for a single array)
    problems = [f"{name}: the dataset has {obs_arrays[name].shape[1:] if name in obs_arrays else 'nothing'}, "
                f"the network reads {tuple(leaf.shape)}" for name, leaf in wanted.items()
                if name not in obs_arrays or obs_arrays[name].shape[1:] != tuple(leaf.shape)]
    if problems:
        raise DatasetError(f"{dataset.path}: its observations do not fit this network's environment: "
                           + "; ".join(problems))
    obs = tree_from_arrays({name: np.asarray(obs_arrays[name], wanted[name].dtype) for name in wanted},
                           template)["obs"]
    return CloningData(jax.device_put(obs), jax.device_put(steps["action"]))


def is_kinetix_dataset(path: str | Path) -> bool:
    """Whether `path` holds a dataset in Kinetix's offline format (a zarr format 2 group) rather than ours."""
    return (Path(path) / ".zgroup").is_file()


def kinetix_cloning_data(path: str | Path, agent: Agent, validation_fraction: float,
                         seed: int) -> tuple[CloningData, CloningData]:
    """(train, held out) from a dataset in Kinetix's offline format: the transitions its `mask` marks, as our
    observations of their states and their actions, split at random by `seed`."""
    transitions = read_kinetix_offline(path, agent.spec.sizes)
    obs = kinetix_offline_observations(transitions, functools.partial(observe, agent.spec))
    rows = np.flatnonzero(np.asarray(transitions.mask, bool))
    order = np.random.default_rng(seed).permutation(rows)
    held = int(round(len(rows) * validation_fraction))
    take = lambda chosen: CloningData(jax.tree.map(lambda leaf: leaf[np.sort(chosen)], obs),  # noqa: E731
                                      jnp.asarray(transitions.action[np.sort(chosen)]))
    return take(order[held:]), take(order[:held])


def _named_shapes(tree: Any) -> dict[str, Any]:
    return {path_name(path): leaf for path, leaf in jax.tree_util.tree_leaves_with_path(tree)}


def negative_log_likelihood(agent: Agent, params: Any, obs: Any, action: Array) -> Array:
    """Mean of -log pi(recorded action | observation) over a batch."""
    dist_params, _ = agent.apply(params, obs)
    return -jnp.mean(agent.distribution.log_prob(dist_params, action))


def _agreement(agent: Agent, params: Any, obs: Any, action: Array) -> Array:
    dist_params, _ = agent.apply(params, obs)
    same = agent.distribution.mode(dist_params) == action
    return jnp.mean(same.reshape(same.shape[0], -1).all(axis=1))


def clone(agent: Agent, params: Any, train: CloningData, held_out: CloningData, config: BCConfig, seed: int,
          on_epoch: Callable[[EpochStats], None] | None = None) -> Any:
    """Parameters after `config.epochs` epochs of cloning from `params` (see the module docstring);
    `on_epoch` hears each epoch's statistics."""
    if train.steps == 0:
        raise DatasetError("no steps to learn from: no episode passes the selection (bc.solved_only, "
                           "bc.min_return)")
    batch = min(config.batch_size, train.steps)
    batches = train.steps // batch
    optimizer = optax.adam(config.learning_rate)

    def step(carry: tuple[Any, Any], rows: Array) -> tuple[tuple[Any, Any], Array]:
        params, opt_state = carry
        obs = jax.tree.map(lambda leaf: leaf[rows], train.obs)
        loss, grads = jax.value_and_grad(lambda p: negative_log_likelihood(agent, p, obs, train.action[rows]))(
            params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), loss

    @jax.jit
    def epoch(params: Any, opt_state: Any, key: Array) -> tuple[Any, Any, Array]:
        order = jax.random.permutation(key, train.steps)[: batches * batch].reshape(batches, batch)
        (params, opt_state), losses = jax.lax.scan(step, (params, opt_state), order)
        return params, opt_state, losses.mean()

    @jax.jit
    def judge(params: Any) -> tuple[Array, Array]:
        return (negative_log_likelihood(agent, params, held_out.obs, held_out.action),
                _agreement(agent, params, held_out.obs, held_out.action))

    opt_state = optimizer.init(params)
    key = jax.random.PRNGKey(seed)
    for number in range(1, config.epochs + 1):
        started = time.perf_counter()
        key, epoch_key = jax.random.split(key)
        params, opt_state, loss = epoch(params, opt_state, epoch_key)
        held_loss, agreement = judge(params) if held_out.steps else (jnp.nan, jnp.nan)
        stats = EpochStats(number, float(loss), float(held_loss), float(agreement), time.perf_counter() - started)
        if on_epoch is not None:
            on_epoch(stats)
    return params
