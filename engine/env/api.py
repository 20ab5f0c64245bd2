"""`make_env`: the environment as a library, in gymnax's functional style, for research code that wants the task
without Impulse's trainer:

    import jax
    import impulse

    env = impulse.make_env(levels="handmade", size="s")
    obs, state = env.reset(jax.random.PRNGKey(0))
    action = env.sample_action(jax.random.PRNGKey(1))
    obs, state, reward, done, info = env.step(jax.random.PRNGKey(2), state, action)

`reset` and `step` are pure functions of their arguments, so they jit and vmap (`jax.vmap(env.step)` over keys,
states and actions runs a batch of environments). Each reset, and each automatic reset when an episode ends inside
`step`, starts one level of the set drawn uniformly with the key given. This module is a face over the engine's own
`engine.env.env.reset_from_batch` and `step`, which it calls unchanged (their docstrings describe one step, the
reward and `info`); the trainer and the services use those directly.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import jax

from impulse.engine.env.actions import ActionSpace, action_space, noop_action, random_action
from impulse.engine.env.config import EnvConfig
from impulse.engine.env.env import reset_from_batch, step
from impulse.engine.env.spec import EnvParams, EnvSpec, env_from_config
from impulse.engine.env.state import EnvState
from impulse.engine.levels.level import Level
from impulse.engine.levels.sets import RANDOM, load_level_set

Array = jax.Array


@dataclass(frozen=True, eq=False)
class Env:
    """An environment over a fixed set of K levels. `spec` and `params` are the engine's; `levels` is the batch of
    levels [K] and `level_names` their names, in the same order."""

    spec: EnvSpec
    params: EnvParams
    levels: Level
    level_names: tuple[str, ...]

    @property
    def num_levels(self) -> int:
        return len(self.level_names)

    @property
    def action_space(self) -> ActionSpace:
        """Shape, dtype and range of an action (`engine.env.actions.ActionSpace`)."""
        return action_space(self.spec)

    def _draw_level(self, key: Array) -> Array:
        return jax.random.randint(key, (), 0, self.num_levels)

    def reset(self, key: Array) -> tuple[Any, EnvState]:
        """A new episode on a level drawn with `key`: (observation, state)."""
        return reset_from_batch(self.spec, self.params, self.levels, self._draw_level(key))

    def step(self, key: Array, state: EnvState, action: Array) -> tuple[Any, EnvState, Array, Array, dict[str, Array]]:
        """One agent step: (observation, state, reward, done, info). When the episode ends, the returned state and
        observation already belong to the next episode, on a level drawn with `key`; `info` describes the episode
        that ended (`engine.env.env`)."""
        state = dataclasses.replace(state, next_level=self._draw_level(key))
        return step(self.spec, self.params, state, action, self.levels)

    def sample_action(self, key: Array) -> Array:
        """A uniformly random action."""
        return random_action(self.spec, key)

    def noop_action(self) -> Array:
        """The action that drives nothing."""
        return noop_action(self.spec)


def make_env(levels: str = "handmade", size: str = "s", observation: str = "entity", action: str = "multi_discrete",
             **options: Any) -> Env:
    """An environment over the level set `levels` (anything `env.levels` takes except "random": "handmade",
    "handmade:NAME,...", "kinetix:s", a level file or a folder of them), in Kinetix size class `size`, with the
    observation ("entity", "symbolic", "symbolic_padded", "pixels", "blind") and action ("multi_discrete",
    "continuous", "discrete") types named. `options` are the other `EnvConfig` fields (frame_skip,
    max_timesteps, dense_reward_scale, pixel_downscale, solver, physics_backend). Raises ValueError naming what is
    wrong."""
    if levels == RANDOM:
        raise ValueError("make_env plays a fixed level set (\"handmade\", \"kinetix:s\", a file or a folder); "
                         "random levels are drawn by the curriculum during training (impulse train "
                         "env.levels=random), or by impulse.engine.levels.generator.sample_random_level")
    known = {f.name for f in dataclasses.fields(EnvConfig)} - {"levels", "size", "observation", "action"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"make_env: unknown option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    spec, params = env_from_config(EnvConfig(levels=levels, size=size, observation=observation, action=action,
                                             **options))
    names, batch = load_level_set(levels, spec.sizes)
    return Env(spec, params, batch, tuple(names))
