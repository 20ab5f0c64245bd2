"""One process of a learner group on loopback (`learner.hosts`): run with `<index> <count> <coordinator>` in
`count` processes at once. Every process builds the same batch of NUM_ENVS environments, computes the
single-process PPO update on all of it on its own device (the reference), then joins the group and runs the
group's update on its own share of the environments only (`learner.hosts.global_batch`). It prints, as one JSON
line, how far the group's parameters and metrics are from the reference, and what the group's collectives gave.
A script, not a test module: `jax.distributed` is joined once per process, before any computation."""

from __future__ import annotations

import json
import sys

import jax
import numpy as np

from impulse.actors.trajectory import EpisodeStats
from impulse.learner.hosts import broadcast_from_leader, global_batch, join_hosts, local_copy
from impulse.learner.sharding import DataParallel, learner_devices
from tests.support.sharded_update_check import NUM_ENVS, update_case


def main() -> None:
    index, count, coordinator = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    group = join_hosts(count, coordinator, index)
    params, batch, key, update, fresh_state = update_case()

    # The reference: one process, one device, the whole batch.
    reference, reference_metrics = jax.device_get(jax.jit(update)(fresh_state(), batch, key))

    # The group: this process holds environments [index * share, (index + 1) * share) of the same batch, and saw
    # `index + 1` episodes end, all solved.
    share = NUM_ENVS // count
    mine = slice(index * share, (index + 1) * share)
    local = jax.device_get(batch)._replace(
        steps=jax.tree.map(lambda x: np.asarray(x)[:, mine], batch.steps),
        bootstrap_obs=jax.tree.map(lambda x: np.asarray(x)[mine], batch.bootstrap_obs),
        train_mask=np.asarray(batch.train_mask)[:, mine],
        behaviour_version=np.asarray(3 - index, np.int32),
        episodes=EpisodeStats(*(np.asarray(index + 1, np.asarray(leaf).dtype) for leaf in batch.episodes)))
    parallel = DataParallel(learner_devices(1))
    group_update = parallel.jit_update(lambda s, b, k: update(s, b, k, minibatch_sharding=parallel.minibatches),
                                       batch)
    placed = global_batch(local, parallel.batch_shardings(batch), group)
    compiled = group_update.lower(parallel.replicate(fresh_state()), placed, key).compile()
    state, metrics = compiled(parallel.replicate(fresh_state()), placed, key)
    state, metrics = local_copy(state), local_copy(metrics)

    param_error = max(float(np.max(np.abs(a - b))) for a, b in zip(jax.tree.leaves(state.params),
                                                                    jax.tree.leaves(reference.params)))
    moved = max(float(np.max(np.abs(a - b))) for a, b in zip(jax.tree.leaves(reference.params),
                                                              jax.tree.leaves(params)))
    compared = [name for name in reference_metrics if name != "policy_lag"]
    metric_error = max(abs(float(metrics[name]) - float(reference_metrics[name])) for name in compared)
    agreed = group.agree(have_batch=index == 0, stopping=False)
    handed = broadcast_from_leader({"seed": np.asarray(100 + index)}, group)
    print(json.dumps({
        "index": index,
        "processes": jax.process_count(),
        "mesh_devices": parallel.size,
        "local_envs": sorted({shard.data.shape[1] for shard in placed.train_mask.addressable_shards}),
        "all_reduce": "all-reduce" in compiled.as_text(),
        "param_max_abs_error": param_error,
        "metric_max_abs_error": metric_error,
        "params_moved_by_update": moved,
        "version": int(state.policy_version),
        "policy_lag": int(metrics["policy_lag"]),
        "episodes": int(placed.episodes.episodes.addressable_data(0)),
        "agreed_have_batch": agreed["have_batch"].tolist(),
        "broadcast_seed": int(handed["seed"]),
    }), flush=True)


if __name__ == "__main__":
    main()
