"""The environment: `reset` and `step`, pure functions of (spec, params, state, ...), vmappable over environments.
They are jitted with `spec` static (so eager calls are fast; inside a caller's jit they simply inline).

One agent step (Kinetix's order, digest section 5.1):
1. the action becomes the unified vector u, then per-slot engine actions through the level's bindings;
2. `spec.frame_skip` physics sub-steps with that action; after each, the sparse reward from the sub-step's contacts
   and the green-blue distance from the new positions; the first sub-step with a non-zero reward decides both
   (otherwise the last sub-step's distance and reward 0);
3. timestep += 1; done = decided, or NaN anywhere in the new simulation state, or timestep >= max_timesteps;
4. dense shaping -(distance - last_distance) * dense_reward_scale, except right after a reset; non-finite -> 0;
5. a NaN state pays reward 0 and is replaced by the reset, so one bad environment never poisons a batch;
6. auto-reset: on done the environment restarts on `levels[state.next_level % K]` (K = size of the caller's level
   batch) and `next_level` advances by 1;
7. the observation is computed once, from the state after the reset selection.

Level batches and auto-reset. `levels` is a `Level` with a leading axis K, handed in by the caller at every step;
that is how a curriculum reaches the environments. Under `jax.vmap` pass it either shared (`in_axes=None`: every
environment walks the same list, each from its own `next_level`, e.g. environment i starting at i as
`reset_from_batch` does) or per environment (`in_axes=0`, levels [E, K]: each environment walks its own queue).
The level an episode was played on is `state.level` (before the step that ends it).

`info` (arrays, one value per environment): `solved`, `failed`, `timed_out`, `nan` (booleans, true only on the step
that ends an episode, mutually exclusive: NaN first, then the sparse outcome, then the time limit),
`returned_episode_return` and `returned_episode_length` (the episode's return and length including this step; the
finished episode's values where done), `distance` (green-blue distance at the deciding sub-step).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from impulse.engine.env.actions import actuation
from impulse.engine.env.observations import observe
from impulse.engine.env.reward import dense_reward, goal_distance, pair_roles, sparse_reward
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.env.state import UNSET_DISTANCE, EnvState, initial_state
from impulse.engine.levels.level import Level
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.state import SimState
from impulse.engine.physics.step import step as physics_step

Array = jax.Array


@functools.partial(jax.jit, static_argnums=0)
def reset(spec: EnvSpec, params: EnvParams, level: Level, next_level: Array | int = 0) -> tuple[Any, EnvState]:
    """Start an episode on `level`; the first auto-reset will take `levels[next_level % K]`."""
    del params  # the start state is the level itself
    state = initial_state(level, next_level)
    return observe(spec, state.sim, state.level, state.timestep), state


@functools.partial(jax.jit, static_argnums=0)
def reset_from_batch(spec: EnvSpec, params: EnvParams, levels: Level, index: Array | int) -> tuple[Any, EnvState]:
    """Start on `levels[index % K]` with `next_level = index + 1`; vmap over index = arange(E) to start E
    environments at staggered places in a shared level batch."""
    index = jnp.asarray(index, jnp.int32)
    num_levels = levels.roles.shape[0]
    level = jax.tree.map(lambda x: x[index % num_levels], levels)
    return reset(spec, params, level, index + 1)


@functools.partial(jax.jit, static_argnums=(0, 3))
def reset_batch(spec: EnvSpec, params: EnvParams, levels: Level, num_envs: int) -> tuple[Any, EnvState]:
    """`num_envs` environments started by `reset_from_batch` at indices 0 .. num_envs - 1 (jitted: it is
    typically called once, outside any other jitted function)."""
    start = jax.vmap(reset_from_batch, in_axes=(None, None, None, 0))
    return start(spec, params, levels, jnp.arange(num_envs, dtype=jnp.int32))


def _has_nan(tree: Any) -> Array:
    flags = [jnp.isnan(x).any() for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
    return functools.reduce(jnp.logical_or, flags, jnp.zeros((), bool))


def _simulate(spec: EnvSpec, params: EnvParams, sim: SimState, level: Level, actions: Array):
    """frame_skip sub-steps; returns (sim, deciding sparse reward, distance at the deciding sub-step)."""
    sizes = spec.sizes
    tables = pair_tables(sizes)
    roles = pair_roles(sim, level, tables)

    def substep(carry, _):
        sim, decided, reward, distance = carry
        sim, contacts = physics_step(sim, params.sim, actions, sizes, spec.solver)
        r = sparse_reward(contacts.touching, roles)
        d = goal_distance(sim.bodies.position, roles, tables)
        reward = jnp.where(decided, reward, r)
        distance = jnp.where(decided, distance, d)
        return (sim, decided | (r != 0), reward, distance), None

    zero = jnp.zeros((), jnp.float32)
    carry = (sim, jnp.zeros((), bool), zero, zero)
    # A scan, not an unrolled loop: measured both faster to run and faster to compile at frame_skip 2 (CPU).
    carry, _ = jax.lax.scan(substep, carry, None, length=spec.frame_skip)
    sim, _, reward, distance = carry
    return sim, reward, distance


@functools.partial(jax.jit, static_argnums=0)
def step(
    spec: EnvSpec,
    params: EnvParams,
    state: EnvState,
    action: Array,
    levels: Level,
    key: Array | None = None,
) -> tuple[Any, EnvState, Array, Array, dict[str, Array]]:
    """One agent step with auto-reset from `levels` (see the module docstring). `key` is accepted for API
    symmetry with stochastic environments and unused: the dynamics are deterministic."""
    del key
    actions = actuation(spec, action, state.level)
    sim, sparse, distance = _simulate(spec, params, state.sim, state.level, actions)

    timestep = state.timestep + 1
    nan = _has_nan(sim)
    decided = sparse != 0
    timed_out = timestep >= spec.max_timesteps
    done = decided | nan | timed_out
    reward = sparse + dense_reward(distance, state.last_distance, params.dense_reward_scale, UNSET_DISTANCE)
    reward = jnp.where(nan, 0.0, reward)
    episode_return = state.episode_return + reward
    episode_length = state.episode_length + 1

    stepped = EnvState(
        sim=sim,
        level=state.level,
        timestep=timestep,
        last_distance=jnp.where(done, UNSET_DISTANCE, distance),
        episode_return=episode_return,
        episode_length=episode_length,
        next_level=state.next_level,
    )
    num_levels = levels.roles.shape[0]
    fresh = initial_state(jax.tree.map(lambda x: x[state.next_level % num_levels], levels), state.next_level + 1)
    new_state = jax.tree.map(lambda a, b: jnp.where(done, a, b), fresh, stepped)
    obs = observe(spec, new_state.sim, new_state.level, new_state.timestep)

    info = {
        "solved": (sparse > 0) & ~nan,
        "failed": (sparse < 0) & ~nan,
        "timed_out": timed_out & ~decided & ~nan,
        "nan": nan,
        "returned_episode_return": episode_return,
        "returned_episode_length": episode_length,
        "distance": jnp.where(jnp.isfinite(distance), distance, 0.0),
    }
    return obs, new_state, reward, done, info
