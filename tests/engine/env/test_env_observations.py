"""Observation layouts (Kinetix digest section 7): shapes, feature positions, masks and attention channels."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.env.observation_types import (
    ATTENTION_CHANNELS,
    CIRCLE_FEATURES,
    JOINT_FEATURES,
    POLYGON_FEATURES,
    THRUSTER_FEATURES,
)
from impulse.engine.env.observations import observation_shape, observe, symbolic_length, symbolic_padded_shape
from impulse.engine.env.spec import EnvSpec
from impulse.engine.levels.level import level_from_scene
from impulse.engine.physics import (
    SIZE_L,
    SIZE_M,
    SIZE_S,
    SceneSizes,
    add_circle,
    add_fixed_joint,
    add_polygon,
    add_rectangle,
    add_revolute_joint,
    add_thruster,
    empty_scene,
)
from tests.support.env_scenes import GREEN_BALL, SPEC, quiet_scene, rollout, start
from tests.support.paths import REPO

observe_jit = jax.jit(observe, static_argnums=0)
GRAVITY_FEATURE = -0.981
PADDED_SHAPES = {SIZE_S: (6, 41), SIZE_M: (10, 45), SIZE_L: (21, 59)}  # Kinetix digest 7.3
KINETIX_OBSERVATIONS = REPO / "tests" / "fixtures" / "kinetix" / "observations.npz"
"""Kinetix 3.0.2's own observations of every shared level's first state (benchmarks/_reference_observations.py)."""
SHARED_LEVELS = REPO.parent / "shared" / "kinetix-levels"


@pytest.mark.parametrize(("sizes", "length"), [(SIZE_S, 140), (SIZE_M, 247), (SIZE_L, 679)], ids=["s", "m", "l"])
def test_shapes(sizes, length):
    P, C, J, T, N = sizes.num_polygons, sizes.num_circles, sizes.num_joints, sizes.num_thrusters, sizes.num_bodies
    entity = observation_shape(EnvSpec(sizes=sizes))
    expected = {
        "polygons": (P, POLYGON_FEATURES),
        "circles": (C, CIRCLE_FEATURES),
        "joints": (2 * J, JOINT_FEATURES),
        "thrusters": (T, THRUSTER_FEATURES),
        "polygon_mask": (P,),
        "circle_mask": (C,),
        "joint_mask": (2 * J,),
        "thruster_mask": (T,),
        "joint_indexes": (2 * J, 2),
        "thruster_indexes": (T,),
        "attention_mask": (ATTENTION_CHANNELS, N, N),
    }
    assert {k: getattr(entity, k).shape for k in expected} == expected
    assert entity.attention_mask.dtype == bool and entity.joint_indexes.dtype == np.int32
    assert symbolic_length(sizes) == length
    flat = observation_shape(EnvSpec(sizes=sizes, observation="symbolic"))
    assert flat.shape == (length,) and flat.dtype == np.float32
    padded = observation_shape(EnvSpec(sizes=sizes, observation="symbolic_padded"))
    assert padded.shape == symbolic_padded_shape(sizes) == PADDED_SHAPES[sizes] and padded.dtype == np.float32
    blind = observation_shape(EnvSpec(sizes=sizes, observation="blind", max_timesteps=40))
    assert blind.shape == (41,) and blind.dtype == np.float32


def _feature_scene():
    """S: a triangle (density 2.5, blue) with a wheel pinned to it (motor binding 3, limits), a small red ball
    with a thruster (binding 1)."""
    state = empty_scene(SIZE_S)
    state, tri = add_polygon(state, (2.0, 2.0), [(-0.3, -0.2), (0.0, 0.4), (0.3, -0.2)], density=2.5)
    state, wheel = add_circle(state, (2.0, 2.0), 0.25)
    state, _ = add_revolute_joint(
        state, tri, wheel, (0.1, 0.0), (0.0, 0.0), motor_on=True, motor_speed=1.5, has_joint_limits=True,
        min_rotation=-0.5, max_rotation=0.7,
    )
    state, ball = add_circle(state, (3.5, 1.0), 0.05, restitution=0.3)
    state, _ = add_thruster(state, ball, (0.01, 0.02), rotation=0.4, power=0.8)
    roles = np.zeros(SIZE_S.num_bodies, np.int32)
    roles[[int(tri), int(wheel), int(ball)]] = [2, 1, 3]
    densities = np.ones(SIZE_S.num_bodies, np.float32)
    densities[int(tri)] = 2.5
    return level_from_scene(state, roles=roles, densities=densities, motor_bindings=[3], thruster_bindings=[1])


def test_entity_features_and_masks():
    level = _feature_scene()
    obs = jax.tree.map(np.asarray, observe_jit(SPEC, level.state, level))
    bodies = jax.tree.map(np.asarray, level.state.bodies)
    tri, wheel, ball = 4, 5, 6

    row = obs.polygons[tri]
    np.testing.assert_allclose(row[0:2], bodies.position[tri])
    np.testing.assert_allclose(row[4:6], [bodies.inverse_mass[tri], bodies.inverse_inertia[tri]])
    assert row[6] == 2.5  # density
    np.testing.assert_array_equal(row[8:12], [0, 0, 1, 0])  # blue
    np.testing.assert_allclose(row[12:14], [0.0, 1.0])  # sin, cos of rotation 0
    assert row[16] == 0.0  # not a circle
    np.testing.assert_allclose(row[17:23], np.asarray(level.state.polygon_vertices[tri, :3]).reshape(-1))
    np.testing.assert_array_equal(row[23:25], [-1.0, -1.0])  # unused fourth vertex
    assert row[25] == 1.0 and np.isclose(row[26], GRAVITY_FEATURE)  # triangle flag, gravity_y / 10
    assert obs.polygons[0, 25] == 0.0  # the floor is a quadrilateral
    np.testing.assert_array_equal(obs.polygon_mask, [True] * 5)

    wheel_row, ball_row = obs.circles
    np.testing.assert_array_equal(wheel_row[8:12], [0, 1, 0, 0])
    np.testing.assert_allclose(wheel_row[16:19], [0.25, 1.0, GRAVITY_FEATURE])
    np.testing.assert_array_equal(ball_row[8:12], [0, 0, 0, 1])
    assert np.isclose(ball_row[15], 0.3)  # restitution
    assert ball_row[5] > 10.0, "entity features are unclipped"

    b_to_a, a_to_b = obs.joints
    np.testing.assert_allclose(b_to_a[:8], [1, 0, 0.0, 0.0, 0.1, 0.0, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(a_to_b[2:6], [0.1, 0.0, 0.0, 0.0])
    motor = [1.5, 1.0, 1.0, 1.0, 0, 0, 0, 1]  # speed, power, on, limits, binding 3
    limits = [np.sin(-0.5), np.cos(-0.5), np.sin(0.7), np.cos(0.7), -0.5, 0.7]  # reference rotation 0
    np.testing.assert_allclose(b_to_a[8:], motor + limits, atol=1e-6)
    np.testing.assert_array_equal(b_to_a[8:], a_to_b[8:])
    np.testing.assert_array_equal(obs.joint_indexes, [[wheel, tri], [tri, wheel]])
    np.testing.assert_array_equal(obs.joint_mask, [True, True])

    np.testing.assert_allclose(obs.thrusters[0], [1, 0.01, 0.02, 0, 1, np.sin(0.4), np.cos(0.4), 0.8], atol=1e-6)
    assert obs.thruster_indexes[0] == ball and obs.thruster_mask[0]

    full, component, jointed, touching = obs.attention_mask
    assert full.all()
    assert component[tri, wheel] and component[wheel, tri] and not component[tri, ball]
    assert np.all(np.diag(component))
    assert jointed[tri, wheel] and jointed[wheel, tri] and jointed.sum() == 2
    # Wheel and triangle overlap (pinned together), so the reset cache is empty but the first step touches.
    assert not touching.any()


def test_attention_channels_follow_joint_components_and_activity():
    sizes = SceneSizes(num_polygons=7, num_circles=2, num_joints=4, num_thrusters=1)
    state = empty_scene(sizes)
    state, box = add_rectangle(state, (1.0, 1.0), 0.4, 0.4)
    state, box2 = add_rectangle(state, (3.0, 3.0), 0.4, 0.4)
    state, ball = add_circle(state, (3.0, 1.0), 0.2)
    state, _ = add_revolute_joint(state, 0, box, (0.0, 5.0), (0.0, 0.0))  # floor - box - left wall
    state, _ = add_revolute_joint(state, box, 1, (0.0, 0.0), (0.0, 0.0))
    state, _ = add_fixed_joint(state, box2, ball, (0.0, 0.0), (0.0, 2.0))
    off = state.bodies.active.at[box2].set(False)  # box2 switched off: invisible in every channel
    level = level_from_scene(state.replace(bodies=state.bodies.replace(active=off)))
    obs = observe_jit(EnvSpec(sizes=sizes), level.state, level)
    full, component, jointed, _ = np.asarray(obs.attention_mask)
    assert component[0, 1] and component[1, 0], "floor and wall share the box: one component"
    assert component[0, box] and component[box, 1] and not component[0, 2]
    assert not jointed[0, 1] and jointed[0, box] and jointed[box, 1] and jointed[1, box]
    assert not jointed[0, 0], "inactive joint slots read (0, 0) and must not mark the floor"
    for channel in (full, component, jointed):
        assert not channel[box2].any() and not channel[:, box2].any()
    assert not component[ball, box2]
    np.testing.assert_array_equal(np.asarray(obs.joint_indexes)[[3, 7]], [[0, 0], [0, 0]])
    assert not np.asarray(obs.joint_mask)[[3, 7]].any()


def test_contact_channel_is_the_last_substep_in_pair_order():
    level = quiet_scene()  # a ball resting on the floor
    state, levels = start([level, level])
    _, (obs, _, _, _, _) = rollout(state, np.zeros((2, 6), np.int32), levels)
    touching = obs.attention_mask[0, 0, 3]
    assert touching[GREEN_BALL, 0], "circle-polygon contacts are stored at [circle, polygon]"
    assert not touching[0, GREEN_BALL]
    assert touching.sum() == 1


def test_symbolic_layout():
    level = _feature_scene()
    spec = EnvSpec(sizes=SIZE_S, observation="symbolic")
    flat = np.asarray(observe_jit(spec, level.state, level))
    entity = jax.tree.map(np.asarray, observe_jit(SPEC, level.state, level))
    clip = lambda x: np.clip(x, -10, 10)  # noqa: E731
    # Floor, then polygon 4 (walls and ceiling dropped), without the gravity column.
    np.testing.assert_allclose(flat[:26], clip(entity.polygons[0, :26]))
    np.testing.assert_allclose(flat[26:52], clip(entity.polygons[4, :26]))
    np.testing.assert_allclose(flat[52:70], clip(entity.circles[0, :18]))
    np.testing.assert_allclose(flat[70:88], clip(entity.circles[1, :18]))
    assert flat[70 + 5] == 10.0, "the small ball's inverse inertia saturates at the clip"
    # Joint: the b -> a row, one-hot(b = wheel), one-hot(a = triangle).
    np.testing.assert_allclose(flat[88:110], clip(entity.joints[0]))
    np.testing.assert_array_equal(flat[110:117], np.eye(7)[5])
    np.testing.assert_array_equal(flat[117:124], np.eye(7)[4])
    np.testing.assert_allclose(flat[124:132], entity.thrusters[0])
    np.testing.assert_array_equal(flat[132:139], np.eye(7)[6])
    assert np.isclose(flat[139], GRAVITY_FEATURE) and flat.shape == (140,)
    # Inactive rows are zeroed: switch the ball off.
    off = level.state.bodies.active.at[6].set(False)
    flat_off = np.asarray(observe_jit(spec, level.state.replace(bodies=level.state.bodies.replace(active=off)), level))
    assert np.all(flat_off[70:88] == 0.0) and np.all(flat_off[:70] == flat[:70])


def test_padded_symbolic_rows_are_the_flat_rows_tagged_with_their_type():
    level = _feature_scene()
    flat = np.asarray(observe_jit(EnvSpec(sizes=SIZE_S, observation="symbolic"), level.state, level))
    padded = np.asarray(observe_jit(EnvSpec(sizes=SIZE_S, observation="symbolic_padded"), level.state, level))
    blocks = [(0, 2, 26, 0), (52, 2, 18, 1), (88, 1, 36, 2), (124, 1, 15, 3)]  # (offset, rows, width, type)
    row = 0
    for offset, rows, width, row_type in blocks:
        for r in range(rows):
            features = padded[row]
            np.testing.assert_array_equal(features[:width], flat[offset + r * width: offset + (r + 1) * width])
            assert np.all(features[width:36] == 0.0)
            np.testing.assert_array_equal(features[36:40], np.eye(4)[row_type])
            assert np.isclose(features[40], GRAVITY_FEATURE)
            row += 1
    assert row == padded.shape[0] == 6


def test_padded_symbolic_and_blind_observations_match_kinetix_on_every_shared_level():
    """Kinetix's SYMBOLIC_FLAT_PADDED, SYMBOLIC_FLAT and BLIND observations of each shared level's first state
    (made by Kinetix's own observation classes) against ours of the same file."""
    from impulse.engine.levels.kinetix_json import load_kinetix_level

    if not SHARED_LEVELS.is_dir():
        pytest.skip(f"Kinetix level files not found at {SHARED_LEVELS} (the shared folder beside the checkout)")
    expected = np.load(KINETIX_OBSERVATIONS)
    names = sorted({key.split("/", 1)[1] for key in expected.files})
    assert len(names) == 42
    for name in names:
        loaded = load_kinetix_level(SHARED_LEVELS / f"{name}.json")
        for kind, ours in (("symbolic_flat_padded", "symbolic_padded"), ("symbolic_flat", "symbolic"),
                           ("blind", "blind")):
            spec = EnvSpec(sizes=loaded.sizes, observation=ours, max_timesteps=256)
            got = np.asarray(observe_jit(spec, loaded.state, loaded.level, 7))
            want = expected[f"{kind}/{name}"]
            assert got.shape == want.shape, (name, kind, got.shape, want.shape)
            np.testing.assert_allclose(got, want, atol=1e-5, rtol=1e-5, err_msg=f"{name} {kind}")


@pytest.mark.parametrize("observation", ["symbolic_padded", "blind"])
def test_padded_and_blind_observations_in_the_env_and_the_flat_network(observation):
    """Reset and step return the observation (blind: the one-hot of the agent step, 0 after a reset), and the
    "flat" network acts on a batch of them."""
    from impulse.engine.env import env
    from impulse.engine.env.actions import action_space
    from impulse.engine.env.spec import EnvParams
    from impulse.learner.agent import make_agent
    from impulse.learner.config import NetworkConfig

    spec = EnvSpec(sizes=SPEC.sizes, observation=observation, max_timesteps=16)
    level = quiet_scene()  # nothing ends an episode but the time limit
    obs, state = env.reset(spec, EnvParams(), level)
    assert obs.shape == observation_shape(spec).shape
    if observation == "blind":
        assert int(np.argmax(obs)) == 0 and obs.sum() == 1.0
    levels = jax.tree.map(lambda x: x[None], level)
    action = jnp.zeros(action_space(spec).shape, jnp.int32)
    obs, state, *_ = env.step(spec, EnvParams(), state, action, levels)
    if observation == "blind":
        assert int(np.argmax(obs)) == 1 and obs.sum() == 1.0
    agent = make_agent(NetworkConfig(kind="flat", width=8, depth=1), spec)
    params = agent.init(jax.random.PRNGKey(0))
    batch = jnp.stack([obs, obs, obs])
    dist_params, value = agent.apply(params, batch)
    assert value.shape == (3,) and dist_params.shape[0] == 3 and np.isfinite(np.asarray(value)).all()
    with pytest.raises(ValueError, match='network.kind "entity" needs env.observation "entity"'):
        make_agent(NetworkConfig(kind="entity"), spec)
