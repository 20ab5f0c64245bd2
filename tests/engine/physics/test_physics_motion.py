"""Free motion and actuators: free fall, thrusters, momentum conservation in collisions, motors, the pendulum."""

from __future__ import annotations

import numpy as np
import pytest

from impulse.engine.physics import add_circle, add_rectangle, add_revolute_joint, add_thruster
from tests.support.physics_sim import (
    DT,
    PARAMS,
    G,
    inertia,
    mass,
    open_scene,
    simulate,
    zero_gravity,
)


def test_free_fall_matches_semi_implicit_euler():
    y0 = 10.0
    state, box = add_rectangle(open_scene(), (2.5, y0), 0.5, 0.5)
    _, trace = simulate(state, 60)
    n = np.arange(1, 61)
    y = trace.position[:, box, 1]
    # Semi-implicit Euler: v_n = -g n dt, y_n = y0 - g dt^2 n (n + 1) / 2 exactly. 1e-4 m covers float32 rounding
    # of 60 additions to a coordinate of about 10 m (ulp ~1e-6 m each).
    np.testing.assert_allclose(y, y0 - G * DT**2 * n * (n + 1) / 2, atol=1e-4, rtol=0)
    np.testing.assert_allclose(trace.velocity[:, box, 1], -G * DT * n, atol=1e-4, rtol=0)
    np.testing.assert_allclose(trace.position[:, box, 0], 2.5, atol=1e-6, rtol=0)
    # Against the continuous y0 - g t^2 / 2 the scheme lags by exactly g dt t / 2 (0.082 m after 1 s): allow
    # that O(dt) difference plus the same rounding.
    t = n * DT
    continuous = y0 - G * t**2 / 2
    assert np.all(np.abs(y - continuous) <= G * DT * t / 2 + 1e-4)
    assert abs(y[-1] - (y0 - G / 2)) < G * DT / 2 + 1e-4


def test_thruster_impulse_magnitude_and_direction():
    body_rotation, thruster_rotation, power = 0.3, 0.7, 1.5
    state = zero_gravity(open_scene())
    state, box = add_rectangle(state, (2.5, 2.5), 1.0, 1.0, density=4.0, rotation=body_rotation)
    state, _ = add_thruster(state, box, (0.0, 0.0), rotation=thruster_rotation, power=power)
    num_steps = 60
    _, trace = simulate(state, num_steps, actions=[0.0, 0.0, 1.0, 0.0])
    momentum = mass(state, box) * trace.velocity[-1, box]
    # Each step adds power * base_thruster_power (10) * dt along the thruster's world direction.
    expected_size = power * PARAMS.base_thruster_power * DT * num_steps
    angle = body_rotation + thruster_rotation
    expected = expected_size * np.array([np.cos(angle), np.sin(angle)])
    # float32 accumulation of 60 equal increments: relative error ~1e-6; 1e-4 relative is the spec.
    assert np.linalg.norm(momentum - expected) <= 1e-4 * expected_size
    # A thruster at the centre of mass applies no torque.
    assert np.max(np.abs(trace.angular_velocity[:, box])) < 1e-6


def test_thruster_off_centre_applies_torque():
    power, offset = 1.0, np.array([0.0, 0.5])
    state = zero_gravity(open_scene())
    state, box = add_rectangle(state, (2.5, 2.5), 1.0, 1.0, density=4.0)
    state, _ = add_thruster(state, box, offset, rotation=0.0, power=power)
    _, trace = simulate(state, 20, actions=[0.0, 0.0, 1.0, 0.0])
    impulse = power * PARAMS.base_thruster_power * DT  # along +x on the first step (body not yet rotated)
    # dw = I^-1 * (r x J) with r = (0, 0.5), J = (impulse, 0): r x J = -0.5 * impulse.
    expected_w = -0.5 * impulse / inertia(state, box)
    np.testing.assert_allclose(trace.angular_velocity[0, box], expected_w, rtol=1e-5)
    np.testing.assert_allclose(
        trace.velocity[0, box], [impulse / mass(state, box), 0.0], rtol=1e-5, atol=1e-7
    )


def _momenta(state, trace, bodies, k):
    """Total linear momentum and angular momentum about the origin of `bodies`: initial state if k is None."""
    m = np.array([mass(state, i) for i in bodies])
    moment = np.array([inertia(state, i) for i in bodies])
    if k is None:
        b = state.bodies
        x, v, w = (np.asarray(a)[bodies] for a in (b.position, b.velocity, b.angular_velocity))
    else:
        x, v, w = trace.position[k, bodies], trace.velocity[k, bodies], trace.angular_velocity[k, bodies]
    linear = (m[:, None] * v).sum(axis=0)
    angular = (moment * w + m * (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0])).sum()
    return linear, angular


def _add_pair(kind: str):
    state = zero_gravity(open_scene())
    if kind == "circle-circle":
        state, a = add_circle(state, (1.5, 2.5), 0.3, velocity=(2.0, 0.1), density=2.0, restitution=0.5)
        state, b = add_circle(
            state, (3.5, 2.7), 0.2, velocity=(-1.0, 0.0), angular_velocity=3.0, restitution=0.5
        )
    elif kind == "box-box":
        state, a = add_rectangle(state, (1.5, 2.5), 0.5, 0.4, velocity=(2.0, 0.1), density=2.0, rotation=0.2)
        state, b = add_rectangle(state, (3.5, 2.7), 0.3, 0.6, velocity=(-1.0, 0.0), angular_velocity=2.0)
    else:
        state, a = add_rectangle(state, (1.5, 2.5), 0.5, 0.4, velocity=(2.0, 0.1), density=2.0, rotation=0.2)
        state, b = add_circle(state, (3.5, 2.7), 0.25, velocity=(-1.0, 0.0), angular_velocity=2.0)
    return state, [int(a), int(b)]


@pytest.mark.parametrize("kind", ["circle-circle", "box-box", "box-circle"])
def test_collision_conserves_momentum(kind):
    state, bodies = _add_pair(kind)
    _, trace = simulate(state, 60)
    # The collision must actually happen (they close at 3 m/s and meet after about 0.5 s): body a loses more than
    # a third of its 2 m/s.
    assert trace.velocity[-1, bodies[0], 0] < 1.3, (
        f"{kind}: no collision: bodies {bodies} passed through each other (v_a = {trace.velocity[-1, bodies[0]]})"
    )
    p0, l0 = _momenta(state, trace, bodies, None)
    p1, l1 = _momenta(state, trace, bodies, -1)
    # Contact impulses are equal and opposite, so momentum changes only by float32 rounding (~1e-7 per impulse,
    # hundreds of impulses): 1e-4 absolute on momenta of order 1.
    np.testing.assert_allclose(p1, p0, atol=1e-4, rtol=0)
    # Both bodies' impulses act at the same contact point, so angular momentum about the origin is kept too.
    assert abs(l1 - l0) < 1e-4


@pytest.mark.parametrize(("action", "motor_speed"), [(1.0, 1.0), (-0.5, 1.0), (0.5, 2.0)])
def test_motor_reaches_target_speed(action, motor_speed):
    state = open_scene()
    state, anchor = add_rectangle(state, (2.5, 2.5), 0.1, 0.1, fixed=True)
    state, wheel = add_circle(state, (2.5, 2.5), 0.3)
    state, _ = add_revolute_joint(
        state, anchor, wheel, (0.0, 0.0), (0.0, 0.0), motor_on=True, motor_speed=motor_speed
    )
    _, trace = simulate(state, 120, actions=[action, 0.0, 0.0, 0.0])
    target = motor_speed * action * PARAMS.base_motor_speed
    relative = trace.angular_velocity[:, wheel] - trace.angular_velocity[:, anchor]
    # Jax2D's motor converges geometrically (gain 1.5 per step, so it overshoots and rings); after 2 s it must
    # be within 5% of the target.
    assert abs(relative[-1] - target) <= 0.05 * abs(target), f"relative spin {relative[-1]} vs {target}"
    # The joint holds the wheel's centre on the anchor against gravity (joint softness: well under 1 cm).
    assert np.max(np.linalg.norm(trace.position[:, wheel] - [2.5, 2.5], axis=1)) < 0.01


def test_pendulum_period():
    length, radius, theta0 = 1.0, 0.1, 0.1
    pivot = np.array([2.5, 4.0])
    state = open_scene()
    state, anchor = add_rectangle(state, pivot, 0.1, 0.1, fixed=True)
    bob_position = pivot + length * np.array([np.sin(theta0), -np.cos(theta0)])
    state, bob = add_circle(state, bob_position, radius)
    state, _ = add_revolute_joint(state, anchor, bob, (0.0, 0.0), pivot - bob_position)
    _, trace = simulate(state, 600)
    arm = trace.position[:, bob] - pivot
    assert np.all(arm[:, 1] < 0)  # it hangs below the pivot
    angle = np.arctan2(arm[:, 0], -arm[:, 1])
    t = np.arange(1, len(angle) + 1) * DT
    k = np.flatnonzero(np.sign(angle[:-1]) != np.sign(angle[1:]))
    crossings = t[k] - angle[k] * DT / (angle[k + 1] - angle[k])  # linear interpolation between steps
    assert len(crossings) >= 6, f"only {len(crossings)} zero crossings in 10 s"
    period = 2 * np.mean(np.diff(crossings))
    # Physical pendulum with the bob's own inertia about the pivot: T = 2 pi sqrt(I_pivot / (m g d)).
    m = mass(state, bob)
    i_pivot = inertia(state, bob) + m * length**2
    expected = 2 * np.pi * np.sqrt(i_pivot / (m * G * length))
    # 3%: the small-angle formula is off by theta0^2 / 16 < 0.1% at 0.1 rad; the rest is the integrator and the
    # soft joint.
    assert abs(period / expected - 1) < 0.03, f"period {period:.4f} s, expected {expected:.4f} s"
    # The amplitude neither grows nor dies out by more than 10% over 5 periods (symplectic integration).
    assert 0.9 * theta0 < np.max(np.abs(angle[-120:])) < 1.1 * theta0
    # The joint keeps the rod length within 5 mm.
    rod = np.linalg.norm(arm, axis=1)
    assert np.max(np.abs(rod - length)) < 0.005
