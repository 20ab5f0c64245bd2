"""A tiny offline dataset in Kinetix's behaviour-cloning format, made INSIDE the reference virtualenv, for the CI
fixture tests/fixtures/kinetix/offline/ (checked by tests/learner/test_kinetix_offline.py).

Like _reference_runner.py, this is the only kind of code that imports Kinetix, and it imports nothing from our
project. Kinetix 3.0.2 reads offline data (`kinetix.data.data_utils`) but ships no writer, so the layout written
here is the one its readers expect: a zarr (format 2) group whose arrays are shards, each a 1-D array of records
(a numpy structured dtype) with the fields

- `action` [action_dim] int32, `action_mask` [action_dim] bool (Kinetix's `get_valid_action_mask_np`), `mask`
  bool, `level_rngs` [2] uint32 (which Kinetix's flat reader drops), and
- one field per leaf of Kinetix's `EnvState`, named by its path: `env_state/polygon/position`,
  `env_state/acc_rr_manifolds/active`, `env_state/timestep`, ... (the names `map_raw_dict_to_action_env_state`
  reads).

Two groups are written:

- `DIR/flat`: one record per transition (2 shards), read by Kinetix's `ZarrBatchDataSource`;
- `DIR/traj`: one record per trajectory (2 shards), every field with a leading [T, 1] (steps, one environment)
  and a `done` field and no `mask`, read by Kinetix's `ZarrTrajDataSource`.

The states are Kinetix's own: each level is loaded with `load_from_json_file` and played by `make_kinetix_env`
(multi-discrete actions) under uniform random actions with fixed keys; a record holds the state an action was
taken in. After writing, both groups are read back with Kinetix's data sources and every leaf of every state,
action and mask must come back bit for bit, which is what makes this Kinetix's format rather than our reading
of it. `DIR/expected.npz` then holds what our reader must reproduce, records in our reading order (shards by
name, records in order, a trajectory's steps in order): `<group>/action`, `<group>/action_mask`,
`<group>/timestep`, `<group>/observation` (Kinetix's `SymbolicObservations` of the record's state) and
`traj/done`.

    .cache/reference-venv/bin/python benchmarks/_reference_offline_dataset.py --out DIR \
        ../shared/kinetix-levels/s/h2_one_wheel_car.json ../shared/kinetix-levels/s/h3_point_the_thruster.json \
        ../shared/kinetix-levels/s/h6_unicycle_right.json

One JSON line reports what was written.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import Any

import flax.serialization
import jax
import numpy as np
import zarr
from kinetix.data.bc_utils import get_valid_action_mask_np
from kinetix.data.data_utils import ZarrBatchDataSource, ZarrTrajDataSource
from kinetix.environment import make_kinetix_env
from kinetix.environment.spaces import ActionType, ObservationType, SymbolicObservations
from kinetix.util.saving import load_from_json_file

sys.path.append(str(Path(__file__).resolve().parent))  # see _reference_common.py
from _reference_common import emit, environment, progress  # noqa: E402

FLAT_CHUNK = 8  # records per zarr chunk: several chunks per shard, the last one partial
TRAJ_SHARDS = ((0, 1), (2,))  # trajectories (by level) in each trajectory shard


def flatten_state(state: Any) -> dict[str, np.ndarray]:
    """Every leaf of a Kinetix EnvState as `env_state/<path>` -> array, 64-bit numbers narrowed to 32 bits (a
    freshly loaded state holds Python scalars for its timestep and last distance)."""
    out: dict[str, np.ndarray] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(f"{prefix}/{key}", value)
            return
        value = np.asarray(node)
        if value.dtype == np.float64:
            value = value.astype(np.float32)
        elif value.dtype == np.int64:
            value = value.astype(np.int32)
        out[prefix] = value

    walk("env_state", flax.serialization.to_state_dict(state))
    return out


def play(env: Any, env_params: Any, level: Any, steps: int, seed: int) -> tuple[list[Any], np.ndarray, np.ndarray]:
    """(states an action was taken in, actions [steps, A], done after each action [steps]) for one level."""
    action_space = env.action_space(env_params)
    key = jax.random.PRNGKey(seed)
    key, reset_key = jax.random.split(key)
    _, state = env.reset(reset_key, env_params, override_reset_state=level)
    states, actions, dones = [], [], []
    for _ in range(steps):
        key, action_key, step_key = jax.random.split(key, 3)
        action = action_space.sample(action_key)
        states.append(state)
        actions.append(np.asarray(action, np.int32))
        _, state, _, done, _ = env.step(step_key, state, action, env_params, override_reset_state=level)
        dones.append(bool(done))
    return states, np.stack(actions), np.asarray(dones)


def record_dtype(columns: dict[str, np.ndarray], leading: tuple[int, ...]) -> np.dtype:
    """The structured dtype of `columns` ([records, *leading, ...] each), one field per column."""
    return np.dtype([(name, value.dtype, leading + value.shape[1 + len(leading):]) for name, value in columns.items()])


def to_records(columns: dict[str, np.ndarray], leading: tuple[int, ...] = ()) -> np.ndarray:
    records = np.zeros(len(next(iter(columns.values()))), record_dtype(columns, leading))
    for name, value in columns.items():
        records[name] = value
    return records


def write_group(path: Path, shards: dict[str, np.ndarray], chunk: int) -> None:
    if path.exists():
        shutil.rmtree(path)
    group = zarr.open_group(str(path), mode="w")
    for name, records in shards.items():
        group.create_dataset(name, data=records, chunks=(chunk,))


def check_equal(what: str, got: Any, want: Any) -> None:
    got, want = np.asarray(got), np.asarray(want)
    if got.shape != want.shape or not np.array_equal(got, want):
        raise SystemExit(f"round trip failed for {what}: {got.shape} vs {want.shape}")


def check_states(group: str, got: Any, want: dict[str, np.ndarray]) -> int:
    """Every leaf of Kinetix's read-back EnvState against the flattened columns written; the leaf count."""
    read = flatten_state(got)
    if set(read) != set(want):
        raise SystemExit(f"{group}: read-back fields differ: {sorted(set(read) ^ set(want))}")
    for name, value in want.items():
        check_equal(f"{group} {name}", read[name], value)
    return len(read)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("levels", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=16, help="flat transitions per level")
    parser.add_argument("--traj-steps", type=int, default=10, help="steps per trajectory (one per level)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if len(args.levels) != 3:
        raise SystemExit("give three levels: the trajectory shards hold levels (0, 1) and (2,)")

    loaded = [load_from_json_file(str(p.resolve())) for p in args.levels]
    static, env_params = loaded[0][1], loaded[0][2]
    env = make_kinetix_env(ActionType.MULTI_DISCRETE, ObservationType.SYMBOLIC_FLAT, None, env_params, static)
    observer = SymbolicObservations(env_params, static)
    observe = jax.jit(jax.vmap(observer.get_obs))

    def columns_of(states: list[Any], actions: np.ndarray) -> dict[str, np.ndarray]:
        flat = [flatten_state(s) for s in states]
        env_state = {name: np.stack([f[name] for f in flat]) for name in flat[0]}
        stacked = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *states)
        mask = get_valid_action_mask_np(stacked, static, actions)
        return {"action": actions, "action_mask": mask, **env_state}, stacked

    # Flat transitions: every level's first `steps` states, split into two shards across a level boundary.
    played = [play(env, env_params, state, max(args.steps, args.traj_steps), args.seed + i)
              for i, (state, _, _) in enumerate(loaded)]
    flat_states = [s for states, _, _ in played for s in states[: args.steps]]
    flat_actions = np.concatenate([a[: args.steps] for _, a, _ in played])
    flat, flat_stacked = columns_of(flat_states, flat_actions)
    n = len(flat_actions)
    rngs = np.asarray(jax.random.split(jax.random.PRNGKey(args.seed + 100), n), np.uint32).reshape(n, 2)
    flat = {"action": flat["action"], "action_mask": flat["action_mask"], "mask": np.ones(n, bool),
            "level_rngs": rngs, **{k: v for k, v in flat.items() if k.startswith("env_state/")}}
    records = to_records(flat)
    cut = n // 2 + 3
    flat_shards = {"shard_000": records[:cut], "shard_001": records[cut:]}
    write_group(args.out / "flat", flat_shards, FLAT_CHUNK)

    # Trajectories: one per level, fields [T, 1, ...] (time, one environment), with `done` and without `mask`.
    T = args.traj_steps
    traj_columns = []
    for states, actions, dones in played:
        columns, _ = columns_of(states[:T], actions[:T])
        columns["done"] = dones[:T]
        traj_columns.append({k: v[:, None][None] for k, v in columns.items()})  # [1, T, 1, ...]
    traj_shards = {}
    for index, levels in enumerate(TRAJ_SHARDS):
        joined = {k: np.concatenate([traj_columns[i][k] for i in levels]) for k in traj_columns[0]}
        traj_shards[f"shard_{index:03d}"] = to_records(joined, (T, 1))
    write_group(args.out / "traj", traj_shards, 1)

    # Kinetix's readers must give back exactly what was written.
    source = ZarrBatchDataSource(str(args.out / "flat"), batch_size=n, seed=args.seed)
    batch = source[0]
    order = np.concatenate([flat_shards[name] for name in source.shard_names])
    leaves = check_states("flat", batch.env_state,
                          {k: order[k] for k in flat if k.startswith("env_state/")})
    for field in ("action", "action_mask", "mask"):
        check_equal(f"flat {field}", getattr(batch, field), order[field])
    num_traj = sum(len(s) for s in traj_shards.values())
    traj_source = ZarrTrajDataSource(str(args.out / "traj"), batch_size=num_traj, seed=args.seed)
    traj_batch = traj_source[0]
    traj_order = np.concatenate([traj_shards[name] for name in traj_source.shard_names])
    check_states("traj", traj_batch.env_state,
                 {k: traj_order[k][:, :, 0] for k in traj_order.dtype.names if k.startswith("env_state/")})
    for field in ("action", "action_mask", "done"):
        check_equal(f"traj {field}", getattr(traj_batch, field), traj_order[field][:, :, 0])
    progress(f"Kinetix read back {n} transitions and {num_traj} trajectories of {T} steps exactly "
             f"({leaves} state leaves)")

    # What our reader must reproduce, in its order: shards by name, records in order, steps in order.
    expected = {
        "flat/action": flat["action"],
        "flat/action_mask": flat["action_mask"],
        "flat/timestep": flat["env_state/timestep"],
        "flat/observation": np.asarray(observe(flat_stacked)),
    }
    traj_records = np.concatenate([traj_shards[name] for name in sorted(traj_shards)])
    traj_flat = {k: traj_records[k][:, :, 0].reshape(-1, *traj_records[k].shape[3:])
                 for k in traj_records.dtype.names}
    traj_states = [s for i in (i for levels in TRAJ_SHARDS for i in levels) for s in played[i][0][:T]]
    traj_stacked = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *traj_states)
    for name, value in flatten_state(traj_stacked).items():
        check_equal(f"traj order {name}", traj_flat[name], value)
    expected.update({
        "traj/action": traj_flat["action"],
        "traj/action_mask": traj_flat["action_mask"],
        "traj/timestep": traj_flat["env_state/timestep"],
        "traj/done": traj_flat["done"],
        "traj/observation": np.asarray(observe(traj_stacked)),
    })
    np.savez_compressed(args.out / "expected.npz", **expected)
    emit({"written": str(args.out), "levels": [p.name for p in args.levels], "flat_records": n,
          "flat_shards": {k: len(v) for k, v in flat_shards.items()}, "trajectories": num_traj,
          "trajectory_steps": T, "state_fields": leaves, "observation_size": int(expected["flat/observation"].shape[1]),
          **environment()})


if __name__ == "__main__":
    main()
