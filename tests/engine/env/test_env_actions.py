"""Action types, their mapping to motors and thrusters, and bindings (Kinetix digest section 6)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from impulse.engine.env.actions import action_space, engine_actions, noop_action, random_action, unified_action
from tests.support.env_scenes import (
    CONTINUOUS_SPEC,
    DISCRETE_SPEC,
    SECOND_CIRCLE,
    SPEC,
    THRUST_ANGLE,
    actuator_scene,
    rollout,
    start,
)

WHEEL = SECOND_CIRCLE - 1
BALL = SECOND_CIRCLE


@pytest.mark.parametrize(
    ("action", "expected"),
    [
        ([0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]),
        ([1, 2, 0, 1, 1, 0], [1, -1, 0, 1, 1, 0]),
        ([2, 2, 2, 2, 1, 1], [-1, -1, -1, -1, 1, 1]),
    ],
)
def test_multi_discrete_mapping(action, expected):
    np.testing.assert_array_equal(unified_action(SPEC, np.asarray(action)), expected)


def test_discrete_mapping():
    table = np.stack([np.asarray(unified_action(DISCRETE_SPEC, a)) for a in range(11)])
    expected = np.zeros((11, 6))
    for motor in range(4):
        expected[2 * motor, motor] = -1.0  # even: -1
        expected[2 * motor + 1, motor] = 1.0  # odd: +1
    expected[9, 4] = expected[10, 5] = 1.0  # 8 is the no-op
    np.testing.assert_array_equal(table, expected)


def test_continuous_passes_through_and_bindings_clip():
    u = unified_action(CONTINUOUS_SPEC, np.asarray([0.5, -2.0, 0.0, 0.0, -0.7, 1.5]))
    np.testing.assert_allclose(u, [0.5, -2.0, 0.0, 0.0, -0.7, 1.5])
    level = actuator_scene(motor_binding=1, thruster_binding=1)
    # Joint 0 reads motor dim 1 clipped to [-1, 1]; thruster 0 reads dim 4 + 1 clipped to [0, 1].
    np.testing.assert_allclose(engine_actions(u, level), [-1.0, 1.0])
    level = actuator_scene(motor_binding=0, thruster_binding=0)
    np.testing.assert_allclose(engine_actions(u, level), [0.5, 0.0])


def test_action_spaces_noop_and_random():
    md, disc, cont = action_space(SPEC), action_space(DISCRETE_SPEC), action_space(CONTINUOUS_SPEC)
    assert md.nvec == (3, 3, 3, 3, 2, 2) and md.num_logits == 16 and md.shape == (6,)
    assert disc.nvec == (11,) and disc.num_logits == 11 and disc.shape == ()
    assert cont.nvec == () and cont.num_logits == 6 and cont.low == (-1, -1, -1, -1, 0, 0)
    for spec in (SPEC, DISCRETE_SPEC, CONTINUOUS_SPEC):
        np.testing.assert_array_equal(unified_action(spec, noop_action(spec)), np.zeros(6))
    keys = jax.random.split(jax.random.PRNGKey(0), 2000)
    sample = np.asarray(jax.vmap(random_action, in_axes=(None, 0))(SPEC, keys))
    assert sample.dtype == np.int32
    for dim, n in enumerate(md.nvec):
        assert set(np.unique(sample[:, dim])) == set(range(n))
    sample = np.asarray(jax.vmap(random_action, in_axes=(None, 0))(DISCRETE_SPEC, keys))
    assert set(np.unique(sample)) == set(range(11))
    sample = np.asarray(jax.vmap(random_action, in_axes=(None, 0))(CONTINUOUS_SPEC, keys))
    assert sample[:, :4].min() < -0.9 and sample[:, :4].max() > 0.9
    assert sample[:, 4:].min() >= 0.0 and sample[:, 4:].max() <= 1.0


def _wheel_spin_and_ball_velocity(spec, actions):
    """Final wheel angular velocity and ball velocity per env after a chunk of held actions."""
    level = actuator_scene()
    state, levels = start([level, level], spec=spec)
    final, (_, _, _, done, _) = rollout(state, np.asarray(actions), levels, spec=spec)
    assert not done.any()
    bodies = final.sim.bodies
    return np.asarray(bodies.angular_velocity[:, WHEEL]), np.asarray(bodies.velocity[:, BALL])


def _check_actuators(spin, velocity):
    # Env 0: motor +1 and thruster on; env 1: motor -1, thruster off. The motor drives w_wheel - w_box (box
    # fixed) towards +-motor_speed * 6 rad/s; the thruster pushes the ball along its direction.
    assert spin[0] > 3.0 and spin[1] < -3.0, spin
    speed = np.linalg.norm(velocity[0])
    assert speed > 0.5
    np.testing.assert_allclose(velocity[0] / speed, [np.cos(THRUST_ANGLE), np.sin(THRUST_ANGLE)], atol=1e-3)
    np.testing.assert_allclose(velocity[1], 0.0, atol=1e-6)


def test_multi_discrete_drives_motor_and_thruster():
    spin, velocity = _wheel_spin_and_ball_velocity(SPEC, [[1, 0, 0, 0, 1, 0], [2, 0, 0, 0, 0, 0]])
    _check_actuators(spin, velocity)


def test_continuous_drives_motor_and_thruster():
    spin, velocity = _wheel_spin_and_ball_velocity(
        CONTINUOUS_SPEC, [[1.0, 0, 0, 0, 1.0, 0], [-1.0, 0, 0, 0, -1.0, 0]]
    )
    _check_actuators(spin, velocity)


def test_discrete_drives_motor_or_thruster():
    # Discrete actions drive one thing at a time: 1 = motor 0 at +1, 0 = motor 0 at -1, 9 = thruster 0.
    spin, _ = _wheel_spin_and_ball_velocity(DISCRETE_SPEC, [1, 0])
    assert spin[0] > 3.0 and spin[1] < -3.0
    spin, velocity = _wheel_spin_and_ball_velocity(DISCRETE_SPEC, [9, 8])
    np.testing.assert_allclose(spin, 0.0, atol=1e-6)
    speed = np.linalg.norm(velocity[0])
    assert speed > 0.5 and np.allclose(velocity[0] / speed, [np.cos(THRUST_ANGLE), np.sin(THRUST_ANGLE)], atol=1e-3)
    np.testing.assert_allclose(velocity[1], 0.0, atol=1e-6)


def test_bindings_route_actions():
    # Motor bound to dim 2, thruster to thruster dim 1: dims 0 and 4 do nothing, dims 2 and 5 drive them.
    level = actuator_scene(motor_binding=2, thruster_binding=1)
    state, levels = start([level, level])
    actions = np.asarray([[1, 1, 0, 1, 1, 0], [0, 0, 1, 0, 0, 1]])
    final, _ = rollout(state, actions, levels)
    spin = np.asarray(final.sim.bodies.angular_velocity[:, WHEEL])
    velocity = np.asarray(final.sim.bodies.velocity[:, BALL])
    np.testing.assert_allclose(spin[0], 0.0, atol=1e-6)
    np.testing.assert_allclose(velocity[0], 0.0, atol=1e-6)
    assert spin[1] > 3.0 and np.linalg.norm(velocity[1]) > 0.5
