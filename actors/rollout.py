"""The rollout: a batch of environments driven by the policy for T steps, as one `lax.scan`.

This is the only place experience is generated. The fused trainer calls it inside its jitted loop; actor
processes call it (jitted on its own) and publish what it returns. It knows nothing of networks: it takes a
`policy(params, obs, key) -> (action, log_prob, value)` over a batch of observations, so any network fits. The
stepping itself is the engine's one episode loop (`engine.env.episodes.episode_loop`); the rollout adds the policy
and what training keeps of each step.

Levels reach the environments through `levels` (a `Level` batch of K, shared by all environments): an episode
that ends restarts on the next level of the batch (see `engine.env.env.reset_batch`). Every step records the id of
the level it was played on (`EnvState.level`), so results are credited by level id even when the caller swaps the
batch while episodes are running (`curriculum.results.level_results`). The caller wraps the steps into a
`TrajectoryBatch` with the bootstrap observation (`carry.obs` after the rollout), its policy version and the train
mask.

Train flags. A curriculum may hand out levels only to evaluate them (robust PLR scores new levels without training
on them), so every environment carries the flag of the episode it is playing (`RolloutCarry.trains`). An episode
takes its flag from the batch it starts from (`train[k]` for level k of `levels`, the level the auto-reset picks),
and keeps it when the caller swaps the batch before it ends, just as it keeps its level.

Watching. A live view (`monitor`) needs more than training does: where every body of a few environments is at
every step and what the action drove. `watch=W` records that for the first W environments (`Watched`, [T, W]); it
costs a slice per step and stays on the device until someone copies it. With the default `watch=0` nothing is
recorded and the compiled rollout is the training one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from impulse.actors.trajectory import EpisodeStats, Trajectory
from impulse.engine.env.actions import actuation
from impulse.engine.env.env import reset_batch
from impulse.engine.env.episodes import LoopCarry, Step, episode_loop
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.env.state import EnvState
from impulse.engine.levels.level import Level

Array = jax.Array
Policy = Callable[[Any, Any, Array], tuple[Array, Array, Array]]


class RolloutCarry(NamedTuple):
    """What one rollout hands to the next."""

    env_state: EnvState  # [E]
    obs: Any  # [E, ...] observation of env_state
    key: Array
    trains: Array  # [E] bool: the episode each environment is playing is trained on


class Watched(NamedTuple):
    """The watched environments at each step: [T, W] leading axes."""

    state: EnvState  # before the step (the scene the action was chosen in)
    actuation: Array  # [T, W, J + T_thrusters] what the action drove: motor commands, then thrust


class RolloutResult(NamedTuple):
    carry: RolloutCarry
    steps: Trajectory  # [T, E]
    train_mask: Array  # [T, E] the train flag of the episode each step belongs to
    stats: EpisodeStats
    watched: Watched | None  # None unless `watch` > 0


def _train_flags(levels: Level, train: Array | None) -> Array:
    """[K] bool, all true when the caller gives none."""
    num_levels = levels.roles.shape[0]
    return jnp.ones(num_levels, bool) if train is None else jnp.asarray(train, bool)


def start_rollout(
    spec: EnvSpec,
    env_params: EnvParams,
    levels: Level,
    num_envs: int,
    key: Array,
    train: Array | None = None,
) -> RolloutCarry:
    """`num_envs` environments started on `levels` [K] as `reset_batch` staggers them (environment i on level
    i % K), each with the train flag of its level (`train` [K] bool; None: all trained on)."""
    obs, env_state = reset_batch(spec, env_params, levels, num_envs)
    flags = _train_flags(levels, train)
    trains = flags[jnp.arange(num_envs) % flags.shape[0]]
    return RolloutCarry(env_state, obs, key, trains)


def rollout(
    policy: Policy,
    params: Any,
    spec: EnvSpec,
    env_params: EnvParams,
    carry: RolloutCarry,
    levels: Level,
    num_steps: int,
    train: Array | None = None,
    watch: int = 0,
    restart: bool = False,
) -> RolloutResult:
    """Run `num_steps` steps of every environment, episodes that start here taking their train flag from `train`
    [K] bool (None: all trained on); record the first `watch` environments for a live view. `restart`: first start
    every environment afresh on `levels` (as `start_rollout` does), cutting the episodes the carry was playing
    (`ppo.restart_envs`)."""
    flags = _train_flags(levels, train)
    if restart:
        carry = start_rollout(spec, env_params, levels, carry.trains.shape[0], carry.key, train)

    def act(obs: Any, state: EnvState, key: Array) -> tuple[Array, tuple[Array, Array]]:
        action, log_prob, value = policy(params, obs, key)
        return action, (log_prob, value)

    def next_trains(step: Step) -> Array:
        # An episode that ends here is followed by one on levels[next_level % K] (the env's auto-reset rule).
        return jnp.where(step.done, flags[step.state.next_level % flags.shape[0]], step.extra)

    def watched(step: Step) -> Watched | None:
        if watch <= 0:
            return None
        state = jax.tree.map(lambda x: x[:watch], step.state)
        return Watched(state, jax.vmap(lambda a, level: actuation(spec, a, level))(step.action[:watch], state.level))

    def record(step: Step) -> tuple[Trajectory, Array, EpisodeStats, Watched | None]:
        info, done = step.info, step.done
        log_prob, value = step.aux
        finished_return = jnp.where(done, info["returned_episode_return"], 0.0)
        transition = Trajectory(
            obs=step.obs,
            action=step.action,
            log_prob=log_prob,
            value=value,
            reward=step.reward,
            done=done,
            solved=info["solved"],
            truncated=info["timed_out"],
            episode_return=finished_return,
            level_id=step.state.level.level_id,
        )
        episode = EpisodeStats(
            episodes=done.astype(jnp.int32).sum(),
            solved=info["solved"].sum(),
            failed=info["failed"].sum(),
            timed_out=info["timed_out"].sum(),
            nan=info["nan"].sum(),
            return_sum=finished_return.sum(),
            length_sum=jnp.where(done, info["returned_episode_length"], 0).sum(),
        )
        return transition, step.extra, episode, watched(step)

    start = LoopCarry(carry.env_state, carry.obs, carry.key, carry.trains)
    end, (trajectory, train_mask, per_step, trace) = episode_loop(
        spec, env_params, levels, start, num_steps, act, record, next_trains
    )
    stats = jax.tree.map(lambda x: x.sum(), per_step)
    return RolloutResult(RolloutCarry(end.state, end.obs, end.key, end.extra), trajectory, train_mask, stats, trace)
