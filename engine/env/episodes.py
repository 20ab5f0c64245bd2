"""The one episode loop: E environments stepped together for T agent steps, as one `lax.scan`.

Every place that plays environments for a while (the rollout that feeds training, evaluation, the no-op filter,
scripted controllers) is this loop with its own two small functions: `act` chooses the actions and `record`
says what to keep of each step. So auto-reset, level batches and the step's bookkeeping are written once.

Contract of `episode_loop`:

- the environments are a batch [E] (`LoopCarry.state`, `LoopCarry.obs`) stepped by the vmapped `engine.env.env.step`
  with the level batch `levels` [K] shared (`in_axes=None`): an episode that ends restarts on
  `levels[state.next_level % K]`;
- each step, `act(obs, state, key) -> (action [E, ...], aux)` sees the observation and the state before the step and
  a fresh key split from `LoopCarry.key` (None when the carry's key is None, for deterministic actions); `aux` is
  anything the caller wants to keep beside the action (log-probabilities, values);
- `record(step) -> pytree` reads the `Step` (before and after, action, reward, done, info); its outputs are stacked
  along a leading time axis [T, ...] and returned;
- `update(step) -> extra` gives the caller's own carry after the step (`step.extra` is the one before it), for
  running tallies such as the outcome of each environment's first episode (`first_episode`) or per-episode flags.

`first_episodes` is the common special case of playing fresh environments and keeping only how each one's first
episode ended.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.env.env import reset_batch
from impulse.engine.env.env import step as env_step
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.env.state import EnvState
from impulse.engine.levels.level import Level

Array = jax.Array


class LoopCarry(NamedTuple):
    """What the loop carries from step to step and hands back at the end."""

    state: EnvState  # [E]
    obs: Any  # [E, ...] observation of `state`
    key: Array | None  # split once per step for `act`; None for deterministic actions
    extra: Any = None  # the caller's own carry, advanced by `update`


class Step(NamedTuple):
    """One agent step of all E environments, as `record` and `update` see it."""

    obs: Any  # the observation the action was chosen from
    state: EnvState  # the state before the step
    extra: Any  # the caller's carry before the step
    action: Array
    aux: Any  # what `act` returned beside the action
    reward: Array
    done: Array  # the step ended an episode (next_state/next_obs then belong to a fresh one)
    info: dict[str, Array]  # as `engine.env.env.step` documents it
    next_obs: Any
    next_state: EnvState


Act = Callable[[Any, EnvState, Array | None], tuple[Array, Any]]
Record = Callable[[Step], Any]
Update = Callable[[Step], Any]


def episode_loop(
    spec: EnvSpec,
    params: EnvParams,
    levels: Level,
    carry: LoopCarry,
    num_steps: int,
    act: Act,
    record: Record | None = None,
    update: Update | None = None,
) -> tuple[LoopCarry, Any]:
    """Step the environments of `carry` `num_steps` times (see the module docstring). Returns (carry after the
    last step, `record`'s outputs stacked [T, ...], or None without `record`)."""
    step_all = jax.vmap(env_step, in_axes=(None, None, 0, 0, None))

    def one_step(carry: LoopCarry, _) -> tuple[LoopCarry, Any]:
        key, act_key = (None, None) if carry.key is None else jax.random.split(carry.key)
        action, aux = act(carry.obs, carry.state, act_key)
        next_obs, next_state, reward, done, info = step_all(spec, params, carry.state, action, levels)
        step = Step(carry.obs, carry.state, carry.extra, action, aux, reward, done, info, next_obs, next_state)
        extra = carry.extra if update is None else update(step)
        out = None if record is None else record(step)
        return LoopCarry(next_state, next_obs, key, extra), out

    return jax.lax.scan(one_step, carry, None, length=num_steps)


class FirstEpisode(NamedTuple):
    """How each environment's first episode went ([E] each), as far as it has been played."""

    finished: Array  # bool: it has ended
    solved: Array  # bool: it ended with green touching blue
    failed: Array  # bool: it ended with green touching red
    episode_return: Array  # float32: its return so far (final once finished)
    length: Array  # int32: its agent steps so far, the step that ended it included


def first_episode_start(num_envs: int) -> FirstEpisode:
    """The tally before any step."""
    false = jnp.zeros(num_envs, bool)
    return FirstEpisode(false, false, false, jnp.zeros(num_envs, jnp.float32), jnp.zeros(num_envs, jnp.int32))


def first_episode(step: Step) -> FirstEpisode:
    """An `update` for `episode_loop` whose extra carry is a `FirstEpisode`: the tally after `step`."""
    tally: FirstEpisode = step.extra
    live = ~tally.finished
    info = step.info
    return FirstEpisode(
        finished=tally.finished | step.done,
        solved=tally.solved | (live & info["solved"]),
        failed=tally.failed | (live & info["failed"]),
        episode_return=jnp.where(live, info["returned_episode_return"], tally.episode_return),
        length=jnp.where(live, info["returned_episode_length"], tally.length),
    )


def first_episodes(
    spec: EnvSpec,
    params: EnvParams,
    levels: Level,
    num_steps: int,
    act: Act,
    key: Array | None = None,
) -> FirstEpisode:
    """Play one fresh environment per level of `levels` [K] (environment i starts on level i) for `num_steps`
    steps and return how each one's first episode went; what happens after its auto-reset is ignored."""
    num_envs = levels.roles.shape[0]
    obs, state = reset_batch(spec, params, levels, num_envs)
    start = LoopCarry(state, obs, key, first_episode_start(num_envs))
    carry, _ = episode_loop(spec, params, levels, start, num_steps, act, update=first_episode)
    return carry.extra
