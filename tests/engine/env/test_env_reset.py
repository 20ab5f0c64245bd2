"""Auto-reset from the caller's level batch, and NaN containment."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.env import env
from impulse.engine.env.observations import observe
from impulse.engine.levels.level import ROLE_BLUE, stack_levels
from tests.support.env_scenes import (
    BATCH,
    GREEN_BALL,
    NUM_LEVELS,
    PARAMS,
    SPEC,
    drop_scene,
    overlap_scene,
    quiet_scene,
    rollout,
    start,
    take,
)

NOOP = np.zeros((BATCH, 6), np.int32)
XS = (1.0, 2.0, 3.0)  # ball x position of reset level k (identifies it)


def _ball_x(sim_position) -> np.ndarray:
    return np.asarray(sim_position)[..., GREEN_BALL, 0]


def test_auto_reset_walks_the_level_batch():
    # Every level is decided on its first step, so each step ends an episode and takes the next level.
    levels = stack_levels([overlap_scene(x) for x in XS])
    first = overlap_scene(4.0)
    state, _ = start([first, first])
    state = state.replace(next_level=jnp.asarray([0, 2], jnp.int32))
    final, (obs, states, reward, done, info) = rollout(state, NOOP, levels)
    assert done.all() and info["solved"].all()
    # Env 0 walks 0, 1, 2, 0, ...; env 1 starts at 2 and wraps around.
    for env_index, offset in enumerate((0, 2)):
        expected = np.asarray([XS[(offset + t) % NUM_LEVELS] for t in range(len(done))])
        np.testing.assert_allclose(_ball_x(states.sim.bodies.position[:, env_index]), expected)
        np.testing.assert_allclose(_ball_x(states.level.state.bodies.position[:, env_index]), expected)
        np.testing.assert_array_equal(states.next_level[:, env_index], offset + 1 + np.arange(len(done)))
    assert np.all(states.timestep == 0) and np.all(states.episode_length == 0)
    # The observation returned with a reset state is that state's observation.
    np.testing.assert_allclose(obs.circles[:, :, 0, 0], _ball_x(states.sim.bodies.position))
    np.testing.assert_allclose(obs.polygons[:, :, 0, :2], np.broadcast_to([2.5, -4.8], (len(done), 2, 2)))


def test_reset_batch_staggers_environments():
    levels = stack_levels([overlap_scene(x) for x in XS])
    obs, state = env.reset_batch(SPEC, PARAMS, levels, 5)
    np.testing.assert_allclose(_ball_x(state.sim.bodies.position), [XS[i % 3] for i in range(5)])
    np.testing.assert_array_equal(state.next_level, np.arange(1, 6))
    assert obs.polygons.shape == (5, SPEC.sizes.num_polygons, 27)
    single, _ = env.reset(SPEC, PARAMS, take(levels, 1))
    np.testing.assert_array_equal(take(obs, 1).polygons, single.polygons)


def test_nan_ends_the_episode_without_poisoning_the_batch():
    state, levels = start([drop_scene(ROLE_BLUE, gap=1.0), drop_scene(ROLE_BLUE, gap=1.0)])
    # A few healthy steps first, so the episode has a length and a return to report.
    state, _ = rollout(state, NOOP, levels)
    bodies = state.sim.bodies
    velocity = bodies.velocity.at[0, GREEN_BALL, 0].set(jnp.nan)
    state = state.replace(sim=state.sim.replace(bodies=bodies.replace(velocity=velocity)))
    final, (obs, states, reward, done, info) = rollout(state, NOOP, levels)
    assert done[0, 0] and info["nan"][0, 0]
    assert not (info["solved"][0, 0] or info["failed"][0, 0] or info["timed_out"][0, 0])
    assert reward[0, 0] == 0.0
    assert info["returned_episode_length"][0, 0] == 13
    assert np.isfinite(info["returned_episode_return"][0, 0]) and np.isfinite(info["distance"]).all()
    assert states.timestep[0, 0] == 0, "the NaN state was replaced by a fresh episode"
    # Nothing non-finite anywhere afterwards, in either environment.
    for leaf in jax.tree.leaves((obs, final, reward)):
        if np.asarray(leaf).dtype.kind == "f":
            assert np.isfinite(np.asarray(leaf)).all()
    # The healthy neighbour carried on with its episode.
    assert not info["nan"][:, 1].any() and states.timestep[0, 1] == 13


def test_reset_returns_the_level_and_its_observation():
    level = quiet_scene()
    obs, state = env.reset(SPEC, PARAMS, level, next_level=7)
    assert int(state.next_level) == 7 and int(state.timestep) == 0 and float(state.last_distance) == -1.0
    reference = jax.jit(observe, static_argnums=0)(SPEC, level.state, level)
    for a, b in zip(jax.tree.leaves(obs), jax.tree.leaves(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(state.sim.bodies.position, level.state.bodies.position)
