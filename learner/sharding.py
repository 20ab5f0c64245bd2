"""The learner's PPO update on several local devices: data parallel over environments.

A batch too big or too slow for one device is split along its environment axis over a one-dimensional mesh;
parameters and optimizer state are replicated on every device. The update itself is `learner.update.ppo_update`,
unchanged: XLA partitions it (GSPMD) from the shardings of its inputs and of its minibatches, so each device runs
the network and the loss gradient on its share of every minibatch, and the gradient, a mean over the minibatch,
becomes a sum across devices (an all-reduce) before the one optimizer step every device applies identically. The
sharded update therefore computes the same function as the single-device one: the same parameters up to float
summation order (tests/learner/test_sharded_update.py checks 2 and 4 simulated devices).

On several hosts (the `learner.hosts` setting, module `learner.hosts`) the mesh spans every learner process's
devices, process after process, and each process places its own environments (`learner.hosts.global_batch`); the
update is the same program.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from impulse.actors.trajectory import TrajectoryBatch, env_axes
from impulse.learner.config import PPOConfig

ENV_AXIS = "envs"
"""Name of the mesh axis the environments are split over."""


class DeviceError(ValueError):
    """The configured devices cannot run the update (too few visible, or the batch does not split evenly)."""


def learner_devices(count: int) -> list[jax.Device]:
    """The first `count` local devices (at least one) of every learner process, process after process (one
    process unless the learner runs on several hosts). `deploy.runtime.devices.restrict_gpus` has already narrowed
    the GPUs a process sees to the configured ones, so on a GPU machine these are exactly them, in order."""
    devices = jax.local_devices()
    count = max(count, 1)
    if count > len(devices):
        raise DeviceError(f"learner.devices asks for {count} devices but this process sees {len(devices)} "
                          f"({', '.join(str(d) for d in devices)})")
    by_process = [[d for d in jax.devices() if d.process_index == p][:count] for p in range(jax.process_count())]
    return [device for devices in by_process for device in devices]


def check_divisible(ppo: PPOConfig, num_devices: int) -> None:
    """Every minibatch must split evenly: its environments are shared out over the devices."""
    per_minibatch = ppo.num_envs // ppo.num_minibatches
    if per_minibatch % num_devices:
        raise DeviceError(f"{num_devices} devices cannot share minibatches of {per_minibatch} environments "
                          f"(ppo.num_envs={ppo.num_envs} / ppo.num_minibatches={ppo.num_minibatches}): make it a "
                          "multiple of the device count")


class DataParallel:
    """Placement of the update on a mesh of local devices; with one device it places nothing and changes nothing."""

    def __init__(self, devices: Sequence[jax.Device]) -> None:
        self.devices = list(devices)
        self.mesh = Mesh(np.asarray(self.devices), (ENV_AXIS,))
        self.replicated = NamedSharding(self.mesh, PartitionSpec())
        self.minibatches = NamedSharding(self.mesh, PartitionSpec(None, ENV_AXIS))
        """[minibatch, sample, ...] stacks of minibatches, samples env-major (see `ppo_update`)."""

    @property
    def size(self) -> int:
        return len(self.devices)

    def batch_shardings(self, batch: TrajectoryBatch) -> TrajectoryBatch:
        """A sharding per leaf of `batch`: split along its environment axis, scalars replicated."""

        def along(axis: int | None, leaf: Any) -> NamedSharding:
            if axis is None:
                return self.replicated
            spec: list[str | None] = [None] * len(leaf.shape)
            spec[axis] = ENV_AXIS
            return NamedSharding(self.mesh, PartitionSpec(*spec))

        return jax.tree.map(along, env_axes(batch), batch, is_leaf=lambda x: x is None)

    def place_batch(self, batch: TrajectoryBatch) -> TrajectoryBatch:
        """Copy a host batch onto the devices, each getting its environments."""
        return jax.device_put(batch, self.batch_shardings(batch))

    def replicate(self, tree: Any) -> Any:
        """Copy parameters or optimizer state onto every device."""
        return jax.device_put(tree, self.replicated)

    def jit_update(self, update: Callable[..., Any], batch: TrajectoryBatch) -> Callable[..., Any]:
        """`update(state, batch, key) -> (state, metrics)` compiled for the mesh: the batch split, everything else
        replicated, the state donated. `batch` is an example batch (arrays or shapes), for its structure."""
        return jax.jit(
            update,
            in_shardings=(self.replicated, self.batch_shardings(batch), self.replicated),
            out_shardings=self.replicated,
            donate_argnums=0,
        )
