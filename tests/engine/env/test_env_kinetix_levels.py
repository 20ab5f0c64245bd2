"""Every shared Kinetix level loads and plays 256 agent steps of random multi-discrete actions without NaN: one
compiled rollout for the levels of all three sizes, each loaded into size L (the smaller ones padded with inactive
slots, as `load_kinetix_level` pads), vmapped over the levels. One compile instead of one per size: the environment's
step dominates the cost, and playing the S and M levels in the larger scene costs little. Each file must still fit
the size class of its folder. Skipped when the shared levels folder is absent."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.benchmarks._harness import LEVELS_DIR
from impulse.engine.env import env
from impulse.engine.env.actions import random_action
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.levels.level import stack_levels
from impulse.engine.physics import SimParams, size_preset

NUM_STEPS = 256
SIZE_CLASSES = ("s", "m", "l")


@functools.partial(jax.jit, static_argnums=(0, 4))
def _play(spec, params, state, levels, num_steps, key):
    step_batch = jax.vmap(env.step, in_axes=(None, None, 0, 0, None))
    act_batch = jax.vmap(random_action, in_axes=(None, 0))
    num_envs = state.timestep.shape[0]

    def body(state, key):
        actions = act_batch(spec, jax.random.split(key, num_envs))
        obs, state, reward, done, info = step_batch(spec, params, state, actions, levels)
        finite = jnp.all(jnp.stack([jnp.isfinite(x).all() for x in jax.tree.leaves(obs) if x.dtype == jnp.float32]))
        finite &= jnp.isfinite(reward).all()
        return state, (finite, done, info["nan"], reward)

    return jax.lax.scan(body, state, jax.random.split(key, num_steps))


def test_kinetix_levels_play_without_nan():
    paths = {size: sorted((LEVELS_DIR / size).glob("*.json")) for size in SIZE_CLASSES}
    if not any(paths.values()):
        pytest.skip(f"no Kinetix levels under {LEVELS_DIR} (the shared/ folder beside the checkout)")
    sizes = size_preset("l")
    names, loaded = [], []
    for size in SIZE_CLASSES:
        for path in paths[size]:
            level = load_kinetix_level(path, sizes)
            assert level.file_sizes.fits_in(size_preset(size)), f"{path} is larger than size {size.upper()}"
            names.append(f"{size}/{path.name}")
            loaded.append(level)
    assert all(level.params == SimParams() for level in loaded), "the shared levels use Jax2D's default physics"
    assert all(level.frame_skip == 2 for level in loaded)
    levels = stack_levels([level.level for level in loaded])
    spec, params = EnvSpec(sizes=sizes), EnvParams()
    _, state = env.reset_batch(spec, params, levels, len(names))
    _, (finite, done, nan, reward) = _play(spec, params, state, levels, NUM_STEPS, jax.random.PRNGKey(0))
    finite, done, nan = np.asarray(finite), np.asarray(done), np.asarray(nan)
    assert finite.all(), f"non-finite observation or reward at steps {np.flatnonzero(~finite)[:5]}"
    bad = [names[i] for i in np.flatnonzero(nan.any(axis=0))]
    assert not bad, f"NaN state in {bad}"
    # Every environment finishes at least one episode (the time limit is 256 steps).
    assert done.any(axis=0).all()
    assert np.abs(np.asarray(reward)).max() < 2.0
