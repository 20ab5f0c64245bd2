"""Kinetix's soft filter against trivial random levels: levels that doing nothing already solves.

`ratio` x n candidates are sampled; each plays the all-zero action for `num_steps` env steps (all candidates side
by side in the engine's episode loop); a candidate whose first episode ended solved within them gets weight
`trivial_weight`, the rest weight 1; n levels are then drawn without replacement in proportion to the weights.
Soft, as in Kinetix: when too few non-trivial levels exist, trivial ones fill the batch rather than failing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from impulse.engine.env.actions import noop_action
from impulse.engine.env.episodes import Act, first_episodes
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.env.state import EnvState
from impulse.engine.levels.generator import GeneratorConfig, sample_random_level
from impulse.engine.levels.level import Level

Array = jax.Array


@dataclass(frozen=True)
class NoopFilterConfig:
    ratio: int = 2
    """Candidates sampled per level kept."""
    num_steps: int = 64
    """Env steps of the no-op rollout (Kinetix's level_filter_n_steps)."""
    trivial_weight: float = 0.001
    """Sampling weight of a level the no-op policy solves (1 for the others)."""


def _noop(spec: EnvSpec) -> Act:
    """An `act` for the episode loop that drives nothing in any environment."""
    action = noop_action(spec)

    def act(obs: Any, state: EnvState, key: Array | None) -> tuple[Array, None]:
        num_envs = state.timestep.shape[0]
        return jnp.broadcast_to(action, (num_envs, *action.shape)), None

    return act


def noop_solves(spec: EnvSpec, params: EnvParams, level: Level, num_steps: int) -> Array:
    """Whether the first episode of the all-zero policy on `level` (within `num_steps` env steps) is solved."""
    one = jax.tree.map(lambda x: x[None], level)
    return first_episodes(spec, params, one, num_steps, _noop(spec)).solved[0]


def sample_filtered_levels(
    key: Array,
    num_levels: int,
    spec: EnvSpec,
    params: EnvParams,
    generator: GeneratorConfig | None = None,
    config: NoopFilterConfig | None = None,
) -> tuple[Level, Array]:
    """(levels [num_levels], fraction of candidates the no-op policy solved). Jittable with the configs static."""
    generator = generator or GeneratorConfig()
    config = config or NoopFilterConfig()
    sample_key, choice_key = jax.random.split(key)
    candidates = jax.vmap(lambda k: sample_random_level(k, spec.sizes, generator))(
        jax.random.split(sample_key, config.ratio * num_levels)
    )
    trivial = first_episodes(spec, params, candidates, config.num_steps, _noop(spec)).solved
    weights = jnp.where(trivial, config.trivial_weight, 1.0)
    chosen = jax.random.choice(
        choice_key, trivial.shape[0], (num_levels,), replace=False, p=weights / weights.sum()
    )
    return jax.tree.map(lambda x: x[chosen], candidates), trivial.mean()
