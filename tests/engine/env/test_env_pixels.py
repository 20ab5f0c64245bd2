"""The pixel observation: known shapes land on the expected pixels in the expected colours (batched and jitted),
the env step returns it, and the "cnn" network runs on it. Size S, downscale 4 (125 x 125), one compile each."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.env import env
from impulse.engine.env.observations import observation_shape
from impulse.engine.env.pixels import pixel_geometry, render_pixels
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED, Level, level_from_scene
from impulse.engine.physics import SIZE_S, add_circle, add_rectangle, add_revolute_joint, add_thruster, empty_scene
from impulse.learner.agent import make_agent
from impulse.learner.config import NetworkConfig

SIZES = SIZE_S
PPM = pixel_geometry(4).pixels_per_metre  # 25 pixels per metre at downscale 4
BALL_RADIUS = 0.5
SPEC = EnvSpec(sizes=SIZES, observation="pixels", max_timesteps=8)


def colour(rgb: tuple[float, float, float]) -> np.ndarray:
    return np.asarray(rgb, np.float32) / 255.0


BOX = SIZES.num_static_polygons  # the one free polygon slot
BALL = SIZES.num_polygons  # circle slot 0
WHEEL = BALL + 1


def scene(ball_x: jax.Array) -> Level:
    """A free green ball (radius 0.5) at (ball_x, 2.5), a fixed red box 1 x 0.4 centred at (1.0, 4.0) with a
    thruster at (0.7, 4.0) pushing along +x (binding 0: yellow), and a blue wheel (radius 0.2) pinned to the box by
    a motorised joint (binding 1: magenta) at (1.6, 4.0)."""
    state = empty_scene(SIZES)
    state, _ = add_rectangle(state, (1.0, 4.0), 1.0, 0.4, fixed=True)
    state, _ = add_circle(state, jnp.stack([ball_x, jnp.float32(2.5)]), BALL_RADIUS)
    state, _ = add_circle(state, (1.6, 4.0), 0.2)
    state, _ = add_revolute_joint(state, BOX, WHEEL, (0.6, 0.0), (0.0, 0.0), motor_on=True)
    state, _ = add_thruster(state, BOX, (-0.3, 0.0))
    # The builder leaves the joint's world anchor to the first solver step; a level file carries it.
    state = state.replace(joints=state.joints.replace(global_position=jnp.asarray([[1.6, 4.0]], jnp.float32)))
    roles = jnp.zeros(SIZES.num_bodies, jnp.int32).at[BOX].set(ROLE_RED).at[BALL].set(ROLE_GREEN)
    return level_from_scene(state, roles=roles.at[WHEEL].set(ROLE_BLUE), motor_bindings=[1])


@functools.cache
def levels() -> Level:
    """The scene with the ball at x = 2.5 and at x = 3.5, built by one jitted call: a batch of 2 levels."""
    return jax.jit(jax.vmap(scene))(jnp.asarray([2.5, 3.5], jnp.float32))


@functools.cache
def rendered() -> np.ndarray:
    """Both scenes drawn by one vmapped, jitted call: [2, 125, 125, 3]."""
    draw = jax.jit(jax.vmap(lambda lv: render_pixels(lv.state, lv, SIZES, 4)))
    return np.asarray(draw(levels()))


def matches(image: np.ndarray, rgb: tuple[float, float, float]) -> np.ndarray:
    return np.all(np.abs(image - colour(rgb)) < 1e-6, axis=-1)


def test_layout_background_and_floor() -> None:
    images = rendered()
    assert images.shape == (2, 125, 125, 3) and images.dtype == np.float32
    assert images.min() >= 0.0 and images.max() <= 1.0
    image = images[0]
    # [x, y] with y up: the floor (fixed neutral: dark grey) fills the bottom rows, up to y = 0.4 m.
    floor_rows = int(round(0.4 * PPM))
    assert matches(image[:, :floor_rows], (80, 80, 80)).all()
    assert not matches(image[:, floor_rows + 1], (80, 80, 80)).any()
    assert matches(image[0, 124], (255, 255, 255))  # top-left corner: background
    assert matches(image[124, 60], (255, 255, 255))


def test_circle_area_position_and_spoke() -> None:
    for image, ball_x in zip(rendered(), (2.5, 3.5), strict=True):
        below_box = np.arange(125)[None, :] < 90  # the box, wheel and thruster lie above y = 90 px
        green = matches(image, (0, 204, 0))
        spoke = matches(image, (0, 0, 0)) & below_box
        covered = green | spoke
        expected = np.pi * (BALL_RADIUS * PPM) ** 2
        assert abs(covered.sum() - expected) < 0.03 * expected
        xs, ys = np.nonzero(covered)
        assert abs(xs.mean() - ball_x * PPM) < 0.5 and abs(ys.mean() - 2.5 * PPM) < 0.5
        # The spoke of an unrotated circle points straight up from the centre.
        sx, sy = np.nonzero(spoke & (np.abs(np.arange(125)[:, None] - ball_x * PPM) < 4))
        assert sx.size >= BALL_RADIUS * PPM and (sy >= 2.5 * PPM - 1).all()


def test_fixed_box_joint_and_wheel_colours() -> None:
    image = rendered()[0]
    box = matches(image, (127.5, 51, 51))  # fixed red: half brightness
    # Pixels sample the integer points of their index: the box covers x in [12.5, 37.5], y in [95, 105] up to
    # float rounding at the boundary (and the wheel, drawn later, covers its right end).
    thruster = np.zeros_like(box)
    thruster[15:21, 97:103] = True  # the thruster glyph's 6 x 6 window around pixel (18, 100)
    assert (box | thruster)[14:34, 97:104].all()
    xs, ys = np.nonzero(box)
    assert xs.min() >= 12 and xs.max() <= 38 and ys.min() >= 94 and ys.max() <= 106
    assert matches(image, (0, 102, 204)).sum() > 0.8 * np.pi * (0.2 * PPM) ** 2  # free blue wheel
    joint = np.argwhere(matches(image, (255, 0, 255)))  # motor binding 1: magenta, one pixel at downscale 4
    np.testing.assert_array_equal(joint, [[round(1.6 * PPM), round(4.0 * PPM)]])
    # The second scene differs only where the ball moved.
    moved = np.any(rendered()[0] != rendered()[1], axis=-1)
    xs = np.nonzero(moved)[0]
    assert xs.min() >= (2.5 - BALL_RADIUS) * PPM - 1 and xs.max() <= (3.5 + BALL_RADIUS) * PPM + 1


def test_env_reset_and_step_return_pixel_observations() -> None:
    params = EnvParams()
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(None, None, 0)), static_argnums=0)(SPEC, params, levels())
    assert obs.image.shape == (2, 125, 125, 3) and obs.image.dtype == jnp.float32
    np.testing.assert_array_equal(obs.image, rendered())
    np.testing.assert_allclose(obs.global_info, [[-0.981], [-0.981]], rtol=1e-5)
    # The step draws inside the traced function (abstract evaluation: no compile of the physics here).
    step = jax.vmap(env.step, in_axes=(None, None, 0, 0, None))
    stepped = jax.eval_shape(functools.partial(step, SPEC, params), state, jnp.zeros((2, 6), jnp.int32), levels())[0]
    assert stepped.image.shape == (2, 125, 125, 3) and stepped.image.dtype == jnp.float32
    assert stepped.global_info.shape == (2, 1)
    shape = observation_shape(SPEC)
    assert shape.image.shape == (125, 125, 3) and shape.global_info.shape == (1,)


def test_cnn_network_on_pixel_batch() -> None:
    agent = make_agent(NetworkConfig(kind="cnn", width=16, depth=1), SPEC)  # Kinetix's torso, small heads
    params = jax.jit(agent.init)(jax.random.key(0))
    kernels = params["params"]["torso"]
    assert kernels["conv_0"]["kernel"].shape == (8, 8, 3, 16) and kernels["conv_1"]["kernel"].shape == (4, 4, 16, 32)
    assert params["params"]["heads"]["actor_0"]["kernel"].shape[0] == 16 * 16 * 32 + 1
    obs = observation_shape(SPEC)
    batch = type(obs)(image=jnp.asarray(rendered()), global_info=jnp.full((2, 1), -0.981))
    dist_params, value = jax.jit(agent.apply)(params, batch)
    assert dist_params.shape == (2, 16) and value.shape == (2,)
    assert np.all(np.isfinite(dist_params)) and np.all(np.isfinite(value))


def test_wrong_network_and_observation_pairs_are_refused() -> None:
    with pytest.raises(ValueError, match='network.kind "cnn" needs env.observation "pixels", got "entity"'):
        make_agent(NetworkConfig(kind="cnn"), EnvSpec(sizes=SIZES, observation="entity"))
    with pytest.raises(ValueError, match='network.kind "transformer" needs env.observation "entity", got "pixels"'):
        make_agent(NetworkConfig(kind="transformer"), SPEC)
    with pytest.raises(ValueError, match="downscale"):
        EnvSpec(pixel_downscale=3)


def test_thruster_glyph_points_the_way_it_pushes() -> None:
    image = rendered()[0]
    window = image[15:21, 97:103]
    nozzle = np.argwhere(matches(window, (93, 93, 93)))
    flame = np.argwhere(matches(window, (196, 196, 0)) | matches(window, (255, 255, 0)))  # tinted yellow
    assert len(nozzle) >= 2 and len(flame) >= 2
    assert nozzle[:, 0].min() > flame[:, 0].max()  # nozzle ahead (+x), exhaust behind
    assert not matches(image[10:25, 90:110], (255, 0, 255)).any()  # the joint's colour stays at the joint
