"""Sparse reward, episode end and dense shaping (Kinetix digest 5.1-5.3)."""

from __future__ import annotations

import numpy as np

from impulse.engine.env.state import UNSET_DISTANCE
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED, level_from_scene
from impulse.engine.physics import add_circle, add_rectangle, add_revolute_joint, empty_scene
from tests.support.env_scenes import (
    BOX,
    CHUNK,
    GREEN_BALL,
    MAX_TIMESTEPS,
    PARAMS,
    SIZES,
    drop_scene,
    level_batch,
    overlap_scene,
    quiet_scene,
    rollout,
    start,
)

NOOP = np.zeros((2, 6), np.int32)


def _first_done(done: np.ndarray, env: int) -> int:
    assert done[:, env].any(), f"env {env} never finished in {len(done)} steps"
    return int(np.argmax(done[:, env]))


def test_green_onto_blue_solves_and_onto_red_fails():
    state, levels = start([drop_scene(ROLE_BLUE), drop_scene(ROLE_RED)])
    _, (_, states, reward, done, info) = rollout(state, NOOP, levels)
    for env, sparse, outcome in ((0, 1.0, "solved"), (1, -1.0, "failed")):
        t = _first_done(done, env)
        assert t >= 3, "the ball should fall for a few steps before it lands"
        assert info[outcome][t, env]
        other = {"solved", "failed", "timed_out", "nan"} - {outcome}
        assert not any(info[k][t, env] for k in other)
        # Before the landing: no episode end, no outcome flags.
        assert not info[outcome][:t, env].any()
        # Reward = sparse +-1 plus the shaping of the last step: the green-blue centre distance shrinks as the
        # ball falls; with a red box there is no green-blue pair, hence no shaping.
        dense = reward[t, env] - sparse
        if sparse > 0:
            assert 0.0 < dense < 0.05, f"env {env}: terminal reward {reward[t, env]}"
        else:
            assert dense == 0.0 and np.all(info["distance"][: t + 1, env] == 0.0)
        assert np.isclose(info["returned_episode_return"][t, env], reward[: t + 1, env].sum(), atol=1e-5)
        assert info["returned_episode_length"][t, env] == t + 1
        # Auto-reset: the state after the terminal step is a fresh episode.
        assert states.timestep[t, env] == 0
        assert states.last_distance[t, env] == UNSET_DISTANCE
        assert states.episode_return[t, env] == 0.0


def test_dense_reward_follows_distance_and_skips_first_step():
    state, levels = start([drop_scene(ROLE_BLUE, gap=1.5), drop_scene(ROLE_BLUE, gap=1.5)])
    _, (_, _, reward, done, info) = rollout(state, NOOP, levels)
    assert not done[:, 0].any(), "the ball should still be falling"
    distance = info["distance"][:, 0]
    # Ball straight above the box centre: distance = vertical gap between centres, shrinking as it falls.
    assert np.all(np.diff(distance) < 0)
    assert reward[0, 0] == 0.0, "no shaping on the first step after a reset"
    expected = -(distance[1:] - distance[:-1]) * PARAMS.dense_reward_scale
    np.testing.assert_allclose(reward[1:, 0], expected, rtol=1e-4, atol=1e-7)
    assert np.all(reward[1:, 0] > 0)


def test_red_beats_blue_in_the_same_substep():
    # A green ball resting on a blue box and against a red box at once (fixed shapes touch too).
    state = empty_scene(SIZES)
    state, blue = add_rectangle(state, (2.0, 2.0), 1.0, 0.5, fixed=True)
    state, ball = add_circle(state, (2.0, 2.4), 0.2, fixed=True)
    state, red = add_circle(state, (2.3, 2.4), 0.15, fixed=True)
    roles = np.zeros(SIZES.num_bodies, np.int32)
    roles[[int(blue), int(ball), int(red)]] = [ROLE_BLUE, ROLE_GREEN, ROLE_RED]
    both = level_from_scene(state, roles=roles)
    state, levels = start([both, overlap_scene(2.0)])
    _, (_, _, reward, done, info) = rollout(state, NOOP, levels)
    assert done[0].all()
    assert info["failed"][0, 0] and not info["solved"][0, 0]
    assert reward[0, 0] == -1.0, "first step after reset: sparse reward only"
    assert info["solved"][0, 1] and reward[0, 1] == 1.0


def test_jointed_and_inactive_shapes():
    # Kinetix reads overlap regardless of joints: a green ball pinned into a blue box still solves.
    state = empty_scene(SIZES)
    state, box = add_rectangle(state, (2.0, 2.0), 1.0, 0.5, fixed=True)
    state, ball = add_circle(state, (2.0, 2.1), 0.2)
    state, _ = add_revolute_joint(state, box, ball, (0.0, 0.1), (0.0, 0.0))
    roles = np.zeros(SIZES.num_bodies, np.int32)
    roles[[int(box), int(ball)]] = [ROLE_BLUE, ROLE_GREEN]
    jointed = level_from_scene(state, roles=roles)
    # An inactive shape counts as neutral: the blue box switched off never rewards the overlapping ball.
    inactive = overlap_scene(2.0)
    off = inactive.state.bodies.replace(active=inactive.state.bodies.active.at[BOX].set(False))
    inactive = inactive.replace(state=inactive.state.replace(bodies=off))
    state, levels = start([jointed, inactive])
    _, (_, _, reward, done, info) = rollout(state, NOOP, levels)
    assert done[0, 0] and info["solved"][0, 0]
    assert not done[:, 1].any() and np.all(reward[:, 1] == 0.0)
    assert np.all(info["distance"][:, 1] == 0.0), "no green-blue pair among active shapes"


def test_time_limit_ends_the_episode():
    state, levels = start([quiet_scene(), quiet_scene()])
    state, (_, _, _, done, _) = rollout(state, NOOP, levels)
    assert not done.any()
    _, (_, states, reward, done, info) = rollout(state, NOOP, levels)
    t = MAX_TIMESTEPS - CHUNK - 1  # index of agent step MAX_TIMESTEPS within the second chunk
    assert done[t].all() and not done[:t].any() and not done[t + 1 :].any()
    assert info["timed_out"][t].all() and not (info["solved"] | info["failed"] | info["nan"]).any()
    assert np.all(reward == 0.0)
    assert np.all(info["returned_episode_length"][t] == MAX_TIMESTEPS)
    assert np.all(states.timestep[t] == 0) and np.all(states.timestep[t + 1] == 1)
    # No green-blue pair: distance 0, so no shaping ever.
    assert np.all(info["distance"] == 0.0)
    assert GREEN_BALL == SIZES.num_polygons


def test_reset_batch_layout():
    # The helper's reset batch has NUM_LEVELS levels; a sanity check that scenes sit where the tests assume.
    levels = level_batch([drop_scene(ROLE_BLUE)])
    assert levels.roles.shape == (3, SIZES.num_bodies)
    assert int(levels.roles[0, BOX]) == ROLE_BLUE and int(levels.roles[0, GREEN_BALL]) == ROLE_GREEN


def _with_modes(ball_mode: int, box_mode: int):
    level = overlap_scene(2.0)
    bodies = level.state.bodies
    modes = bodies.collision_mode.at[GREEN_BALL].set(ball_mode).at[BOX].set(box_mode)
    return level.replace(state=level.state.replace(bodies=bodies.replace(collision_mode=modes)))


def test_collision_modes_decide_what_touches():
    # Mode 0 meets only mode 2: a mode-0 green ball never touches a mode-1 blue box, but does touch a mode-2 one.
    state, levels = start([_with_modes(0, 1), _with_modes(0, 2)])
    _, (_, _, reward, done, info) = rollout(state, NOOP, levels)
    assert not done[:, 0].any() and np.all(reward[:, 0] == 0.0)
    assert done[0, 1] and info["solved"][0, 1]
