"""Kinetix's soft filter against trivial random levels: levels that doing nothing already solves.

`ratio` x n candidates are sampled; each plays the all-zero action for `num_steps` env steps (replaying the level
when an episode ends); a candidate whose first finished episode was solved gets weight `trivial_weight`, the rest
weight 1; n levels are then drawn without replacement in proportion to the weights. Soft, as in Kinetix: when
too few non-trivial levels exist, trivial ones fill the batch rather than failing.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from engine.env.actions import noop_action
from engine.env.env import reset, step
from engine.env.spec import EnvParams, EnvSpec
from engine.levels.generator import GeneratorConfig, sample_random_level
from engine.levels.level import Level

Array = jax.Array


@dataclass(frozen=True)
class NoopFilterConfig:
    ratio: int = 2
    """Candidates sampled per level kept."""
    num_steps: int = 64
    """Env steps of the no-op rollout (Kinetix's level_filter_n_steps)."""
    trivial_weight: float = 0.001
    """Sampling weight of a level the no-op policy solves (1 for the others)."""


def noop_solves(spec: EnvSpec, params: EnvParams, level: Level, num_steps: int) -> Array:
    """Whether the first episode of the all-zero policy on `level` (within `num_steps` env steps) is solved."""
    replay = jax.tree.map(lambda x: x[None], level)
    _, state = reset(spec, params, level, next_level=0)
    action = noop_action(spec)

    def one_step(carry, _):
        state, finished, solved = carry
        _, state, _, done, info = step(spec, params, state, action, replay)
        solved = solved | (done & ~finished & info["solved"])
        return (state, finished | done, solved), None

    false = jnp.zeros((), bool)
    (_, _, solved), _ = jax.lax.scan(one_step, (state, false, false), None, length=num_steps)
    return solved


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
    trivial = jax.vmap(lambda lv: noop_solves(spec, params, lv, config.num_steps))(candidates)
    weights = jnp.where(trivial, config.trivial_weight, 1.0)
    chosen = jax.random.choice(
        choice_key, trivial.shape[0], (num_levels,), replace=False, p=weights / weights.sum()
    )
    return jax.tree.map(lambda x: x[chosen], candidates), trivial.mean()
