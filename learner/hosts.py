"""The learner on several hosts: one learner process per host, the PPO update data parallel over all of them.

`learner.hosts` processes (one per machine, or several on one machine for a test) join one JAX runtime with
`jax.distributed` (`join_hosts`). Every process then sees every process's devices, and the learner's mesh
(`learner.sharding.DataParallel`) spans them all, process after process. Each process trains on the batches of
its own share of the actors (`serves_actor`), and every update all of them:

1. agree that each holds a batch, or that one of them is stopping (`HostGroup.agree`, a small all-gather);
2. put their batches side by side along the environment axis: the global batch of `hosts` x `ppo.num_envs`
   environments, of which each process holds its own (`global_batch`); the per-batch scalars become the group's
   (episode counts summed, the oldest behaviour version);
3. run the same `ppo_update` as one process would on that global batch. XLA partitions it over the mesh, so the
   gradient of every minibatch is summed across processes (an all-reduce over the network: gloo on CPUs, NCCL on
   GPUs) before the one optimizer step that every process applies, and the parameters stay identical everywhere.

Process 0, the leader, is the learner the rest of the run sees: it publishes the weights and the status, writes
the checkpoints and metrics.jsonl, and restores a resumed run, whose state it then hands to the others
(`broadcast_from_leader`). The other processes take part in the update and acknowledge their actors' batches,
nothing else. A process of the group that dies ends the others (JAX's coordination service notices the missing
heartbeat); the launcher or SLURM starts the group again and it resumes from the leader's newest checkpoint.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils

from impulse.actors.trajectory import EpisodeStats, TrajectoryBatch, env_axes

log = logging.getLogger("impulse.learner")

LEADER = 0
"""The process index that speaks for the group."""


class HostsError(ValueError):
    """The group cannot be formed as configured (no coordinator, no index for this process, a bad index)."""


@dataclass(frozen=True)
class HostGroup:
    """This learner process's place in its group; a group of one is an ordinary learner."""

    count: int = 1
    index: int = LEADER

    @property
    def is_leader(self) -> bool:
        return self.index == LEADER

    @property
    def several(self) -> bool:
        return self.count > 1

    def agree(self, **flags: bool) -> dict[str, np.ndarray]:
        """Every process's value of each flag, as a [count] bool array per flag (in process order). A collective:
        every process of the group calls it with the same flag names at the same point of its cycle."""
        names = sorted(flags)
        if not self.several:
            return {name: np.asarray([flags[name]]) for name in names}
        mine = np.asarray([flags[name] for name in names], np.int32)
        gathered = np.asarray(multihost_utils.process_allgather(mine)).reshape(self.count, len(names))
        return {name: gathered[:, i].astype(bool) for i, name in enumerate(names)}

    def serves_actor(self, actor_index: int) -> bool:
        """Whether this process trains on (and acknowledges) the batches of actor `actor_index`: actors are dealt
        to the processes round robin, so every process has a share as long as there are at least `count`."""
        return actor_index % self.count == self.index

    def name(self, base: str) -> str:
        """This process's name on the bus: `base` for the leader (the learner every other process knows), and
        `base-<index>` for the others."""
        return base if self.is_leader else f"{base}-{self.index}"


ONE_HOST = HostGroup()
"""A learner on one process (the default)."""


def host_index_from_environment() -> int | None:
    """This process's index in the group as a cluster scheduler gives it (SLURM's task rank), if any."""
    value = os.environ.get("SLURM_PROCID")
    return int(value) if value is not None and value.isdigit() else None


def join_hosts(count: int, coordinator: str, index: int | None) -> HostGroup:
    """Join this process to its learner group (before JAX has made any computation or seen any device).

    `coordinator` is `host:port` of process 0 (where the leader's JAX coordination service listens; the other
    processes connect to it); `index` is this process's place in the group, 0 to count-1, from `--host-index` or
    the scheduler (`host_index_from_environment`). A group of one joins nothing."""
    if count <= 1:
        return ONE_HOST
    if index is None:
        index = host_index_from_environment()
    if index is None:
        raise HostsError(f"learner.hosts = {count}: give this process its place in the group with --host-index N "
                         "(0 for the leader), or start it under SLURM (SLURM_PROCID)")
    if not 0 <= index < count:
        raise HostsError(f"--host-index {index} is outside the group of learner.hosts = {count} (0 to {count - 1})")
    if not coordinator:
        raise HostsError(f"learner.hosts = {count} needs learner.coordinator: host:port of the leader "
                         "(--host-index 0), which every learner process can reach")
    # CPU processes reduce over gloo; GPU processes use NCCL whatever this says.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    log.info("learner process %d of %d: joining the group at %s ...", index, count, coordinator)
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=count, process_id=index)
    log.info("learner process %d of %d joined: %d devices in the group, %d here", index, count,
             len(jax.devices()), len(jax.local_devices()))
    return HostGroup(count, index)


def global_batch(local: TrajectoryBatch, shardings: TrajectoryBatch, group: HostGroup) -> TrajectoryBatch:
    """The group's batch from this process's `local` one: the environment-axis leaves are placed as this
    process's part of one global array (`shardings`, from `DataParallel.batch_shardings`); the per-batch scalars,
    which must be the same everywhere, become the group's (a collective, like `agree`): episode counts and sums
added up, the oldest behaviour version (so the update's `policy_lag` is the group's largest), the leader's actor
and sequence number."""
    heads = [local.behaviour_version, local.actor_id, local.seq]
    own = np.asarray([float(np.asarray(x)) for x in (*heads, *local.episodes)], np.float64)
    every = np.asarray(multihost_utils.process_allgather(own)).reshape(group.count, own.size)
    version, actor_id, seq = every[:, 0].min(), every[LEADER, 1], every[LEADER, 2]
    summed = every[:, len(heads):].sum(axis=0)
    stats = EpisodeStats(*(np.asarray(total, np.asarray(leaf).dtype) for total, leaf in zip(summed, local.episodes)))
    scalars = local._replace(behaviour_version=np.asarray(version, np.int32), actor_id=np.asarray(actor_id, np.int32),
                             seq=np.asarray(seq, np.int32), episodes=stats)

    def place(axis: int | None, leaf: Any, sharding: Any) -> jax.Array:
        if axis is None:  # the same value in every process: replicated
            return jax.make_array_from_process_local_data(sharding, np.asarray(leaf), np.shape(leaf))
        return jax.make_array_from_process_local_data(sharding, np.asarray(leaf))

    return jax.tree.map(place, env_axes(scalars), scalars, shardings, is_leaf=lambda x: x is None)


def broadcast_from_leader(tree: Any, group: HostGroup) -> Any:
    """`tree` as the leader holds it, on every process of the group (host arrays of the same structure)."""
    if not group.several:
        return tree
    return multihost_utils.broadcast_one_to_all(jax.device_get(tree), is_source=group.is_leader)


def local_copy(tree: Any) -> Any:
    """Host copies of a tree of replicated arrays, from this process's own replica: what the leader publishes and
    checkpoints (a group-wide array cannot be fetched whole by one process)."""
    return jax.tree.map(lambda leaf: np.asarray(leaf.addressable_data(0)) if isinstance(leaf, jax.Array)
                        else np.asarray(leaf), tree)
