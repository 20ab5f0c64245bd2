"""Scripted controllers for the hand-made levels (`engine.env.play` plays them through the environment).

They prove that a level can be solved within an episode (and show how), and give tests a fixed point: a level
whose controller stops solving it has changed behaviour. A controller is a pure function
`(sim: SimState, t: int32 agent step of the episode) -> multi-discrete action [6] int32` (motor dims 0..3: 0 off,
1 -> +1, 2 -> -1; thruster dims 4, 5: 0 off, 1 on), so it runs inside `jax.lax.scan` and vmaps over levels. Feedback
controllers read bodies by index, so they expect the level built in its own size. `SOLUTIONS` maps level names
to their controller.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.physics.state import SimState

Array = jax.Array
Controller = Callable[[SimState, Array], Array]

OFF, PLUS, MINUS = 0, 1, 2  # motor categories of the multi-discrete action


def action(motor0=OFF, motor1=OFF, thrust0=0, thrust1=0) -> Array:
    """A multi-discrete action from the usual controls (motor bindings 0 and 1, thruster bindings 0 and 1)."""
    values = [motor0, motor1, OFF, OFF, thrust0, thrust1]
    return jnp.stack([jnp.asarray(v).astype(jnp.int32) for v in values])


def noop(sim: SimState, t: Array) -> Array:
    del sim, t
    return jnp.zeros((6,), jnp.int32)


def hold(**controls) -> Controller:
    """The same action at every step (keywords of `action`)."""

    def controller(sim: SimState, t: Array) -> Array:
        del sim, t
        return action(**controls)

    return controller


def burst(steps: int, **controls) -> Controller:
    """The action for the first `steps` agent steps, then nothing."""

    def controller(sim: SimState, t: Array) -> Array:
        del sim
        return jnp.where(t < steps, action(**controls), 0)

    return controller


def duty(period: int, on: int, **controls) -> Controller:
    """The action for the first `on` steps of every `period`, otherwise nothing."""

    def controller(sim: SimState, t: Array) -> Array:
        del sim
        return jnp.where(t % period < on, action(**controls), 0)

    return controller


def sequence(*phases: tuple[int, dict]) -> Controller:
    """Piecewise-constant actions: phases of (last step + 1, controls); the last phase lasts to the end."""

    def controller(sim: SimState, t: Array) -> Array:
        del sim
        chosen = action(**phases[-1][1])
        for until, controls in reversed(phases[:-1]):
            chosen = jnp.where(t < until, action(**controls), chosen)
        return chosen

    return controller


def _cartpole_push(sim: SimState, cart: int, pole: int, target_x: float) -> tuple[Array, Array]:
    """(push right, push left) for a cart carrying a free pole: a bang-bang PD rule that holds the pole at a
    small lean towards `target_x` (less as the cart speeds up) and pushes the cart under it."""
    b = sim.bodies
    x, vx = b.position[cart, 0], b.velocity[cart, 0]
    lean, lean_rate = -b.rotation[pole], -b.angular_velocity[pole]  # positive: leaning right
    lean_ref = jnp.clip(0.05 * (target_x - x) - 0.12 * vx, -0.1, 0.1)
    signal = lean - lean_ref + 0.3 * lean_rate
    return signal > 0.005, signal < -0.005


def cartpole_thrusters(cart: int, pole: int, target_x: float) -> Controller:
    """Balance the pole of a cart pushed by two thrusters (binding 0 right, 1 left) while walking it to
    `target_x`."""

    def controller(sim: SimState, t: Array) -> Array:
        del t
        right, left = _cartpole_push(sim, cart, pole, target_x)
        return action(thrust0=right, thrust1=left)

    return controller


def cartpole_wheels(cart: int, pole: int, target_x: float) -> Controller:
    """The same for a cart on motorised wheels (binding 0: +1 rolls right, -1 left)."""

    def controller(sim: SimState, t: Array) -> Array:
        del t
        right, left = _cartpole_push(sim, cart, pole, target_x)
        return action(motor0=jnp.where(right, PLUS, jnp.where(left, MINUS, OFF)))

    return controller


Waypoint = tuple[float, float, int, float]


def _waypoint(p: Array, waypoints: tuple[Waypoint, ...]) -> tuple[Array, Array]:
    """The first waypoint (x, y, axis, limit) whose gate is still closed (p[axis] < limit); the last one is
    the destination (its gate is ignored)."""
    wx, wy = jnp.asarray(waypoints[-1][0]), jnp.asarray(waypoints[-1][1])
    for x, y, axis, limit in reversed(waypoints[:-1]):
        before = p[axis] < limit
        wx, wy = jnp.where(before, x, wx), jnp.where(before, y, wy)
    return wx, wy


def hover_to(body: int, waypoints: tuple[Waypoint, ...], a_up: float, a_right: float) -> Controller:
    """Fly a body with an upward thruster (binding 0, acceleration `a_up`) and a rightward one (binding 1,
    `a_right`) through waypoints, tracking a velocity towards the current one."""

    def controller(sim: SimState, t: Array) -> Array:
        del t
        b = sim.bodies
        p, v = b.position[body], b.velocity[body]
        wx, wy = _waypoint(p, waypoints)
        vy_want = jnp.clip(2.0 * (wy - p[1]), -1.5, 1.5)
        vx_want = jnp.clip(1.5 * (wx - p[0]), -1.0, 1.0)
        up = (vy_want - v[1]) * 8.0 + 9.81 > a_up / 2
        right = (vx_want - v[0]) * 16.0 > a_right / 2
        return action(thrust0=up, thrust1=right)

    return controller


def lander_two_jets(body: int, waypoints: tuple[Waypoint, ...], jet: float, tilt: float) -> Controller:
    """Fly a craft with two jets at +-`tilt` from vertical (binding 0 pushes up-right, 1 up-left; acceleration
    `jet` each) through waypoints: pick the jet combination whose acceleration is closest to the one a velocity
    tracker asks for."""
    s, c = math.sin(tilt), math.cos(tilt)
    options = np.array([[0.0, 0.0], [s, c], [-s, c], [0.0, 2 * c]], np.float32) * jet  # none, right, left, both
    flags = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.int32)

    def controller(sim: SimState, t: Array) -> Array:
        del t
        b = sim.bodies
        p, v = b.position[body], b.velocity[body]
        wx, wy = _waypoint(p, waypoints)
        v_want = jnp.stack([jnp.clip(1.2 * (wx - p[0]), -1.2, 1.2), jnp.clip(1.5 * (wy - p[1]), -1.2, 1.0)])
        want = (v_want - v) * 6.0 + jnp.array([0.0, 9.81])
        best = jnp.argmin(jnp.sum((jnp.asarray(options) - want) ** 2, axis=1))
        chosen = jnp.asarray(flags)[best]
        return action(thrust0=chosen[0], thrust1=chosen[1])

    return controller


# Accelerations of the thrust-driven bodies (thruster power x base power 10 / mass), for the feedback rules.
_SHELF_BOX_MASS = 0.4 * 0.4
_LANDER_MASS = 0.5 * 0.25 + 2 * 0.05 * math.dist((0.3, -0.3), (0.2, -0.12)) * 0.5

SOLUTIONS: dict[str, Controller] = {
    "s_easy_thrust_right": hold(thrust0=1),
    "s_easy_car_right": hold(motor0=PLUS),
    "s_hop_over": burst(13, thrust0=1),
    "s_lander": duty(5, 2, thrust0=1),
    "s_catapult": hold(motor0=PLUS),
    "m_car_bump": hold(motor0=PLUS),
    "m_thrust_shelf": hover_to(
        4, ((0.6, 2.9, 1, 2.6), (4.3, 2.9, 0, 0.0)), 0.3 * 10 / _SHELF_BOX_MASS, 0.15 * 10 / _SHELF_BOX_MASS
    ),
    "m_cartpole": cartpole_thrusters(cart=4, pole=5, target_x=4.3),
    "m_catapult": duty(3, 1, motor0=PLUS),
    "l_car_climb": hold(motor0=PLUS),
    "l_lander": lander_two_jets(
        4, ((3.0, 3.3, 0, 2.7), (3.9, 0.6, 0, 0.0)), 0.18 * 10 / _LANDER_MASS, math.radians(30.0)
    ),
    "l_cartpole": cartpole_wheels(cart=4, pole=5, target_x=4.2),
    "l_catapult": hold(motor0=PLUS),
    "l_claw": sequence(
        (10, dict(motor1=PLUS)), (120, dict(motor0=PLUS, motor1=PLUS)), (0, dict(motor0=PLUS, motor1=MINUS))
    ),
}
