"""Hand-made level designs (our own, not Kinetix's files).

Each builder takes the scene sizes to build into (default: the smallest Kinetix size it fits) and returns a
`Level`. Geometry is in metres: the arena spans x, y in [0, 5] and the floor's top is at y = 0.4. Roles: green is
the object to deliver, blue the goal, red kills on contact. Motors are driven by motor binding 0 and thrusters by
thruster binding 0 unless a design says otherwise. Body indices are fixed by the order shapes are added (polygons
from 4, circles from the size's polygon count); `engine.levels.handmade.controllers` relies on them.
"""

from __future__ import annotations

import math

from impulse.engine.levels.handmade.scene_builder import FLOOR, SceneBuilder
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED, Level
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes

GROUND = 0.4  # the floor's top


def _trapezoid(bottom: float, top: float, height: float) -> list[tuple[float, float]]:
    """Clockwise local vertices of a symmetric trapezoid centred on the origin."""
    return [(-top / 2, height / 2), (top / 2, height / 2), (bottom / 2, -height / 2), (-bottom / 2, -height / 2)]


def _pole(b: SceneBuilder, cart: int, base: tuple[float, float], length: float, tilt: float) -> tuple[int, int]:
    """A free (unmotored) pole hinged on `cart` at `base`, leaning `tilt` radians (positive = left), with a green
    ball welded to its top. Returns (pole, ball)."""
    top = (base[0] - length * math.sin(tilt), base[1] + length * math.cos(tilt))
    mid = ((base[0] + top[0]) / 2, (base[1] + top[1]) / 2)
    pole = b.rect(mid, 0.08, length, rotation=tilt, density=0.5)
    b.hinge(cart, pole, base)
    ball = b.circle(top, 0.12, role=ROLE_GREEN, density=0.5)
    b.weld(pole, ball, top)
    return pole, ball


# ---------------------------------------------------------------------------------------------------------------
# Size S: one polygon, two circles, one joint, one thruster.


def s_easy_thrust_right(sizes: SceneSizes = SIZE_S) -> Level:
    """A green box on the floor with a thruster pointing right; the blue ball is 1.7 m away. The thrust only just
    beats floor friction, so random thrusting creeps but rarely arrives; holding it arrives in about 40 steps."""
    b = SceneBuilder(sizes)
    box = b.rect((1.2, GROUND + 0.2), 0.4, 0.4, role=ROLE_GREEN)
    b.thruster(box, direction=0.0, power=0.12)
    b.circle((3.4, GROUND + 0.3), 0.3, role=ROLE_BLUE, fixed=True)
    return b.level()


def s_easy_car_right(sizes: SceneSizes = SIZE_S) -> Level:
    """A motorised green wheel with a trailing tail (motor +1 rolls right); the blue ball waits on the right."""
    b = SceneBuilder(sizes)
    r = 0.25
    wheel = b.circle((1.2, GROUND + r), r, role=ROLE_GREEN)
    tail = b.rect((0.8, GROUND + 0.12), 0.8, 0.12)
    b.hinge(wheel, tail, (1.2, GROUND + r), motor=True, speed=1.0, power=1.0)
    b.circle((4.2, GROUND + 0.3), 0.3, role=ROLE_BLUE, fixed=True)
    return b.level()


def s_hop_over(sizes: SceneSizes = SIZE_S) -> Level:
    """A green box with a thruster angled 65 degrees up-right; a red ball sits between it and the blue one."""
    b = SceneBuilder(sizes)
    box = b.rect((0.7, GROUND + 0.2), 0.4, 0.4, role=ROLE_GREEN)
    b.thruster(box, direction=math.radians(65.0), power=0.3)
    b.circle((2.4, GROUND + 0.35), 0.35, role=ROLE_RED, fixed=True)
    b.circle((4.1, GROUND + 0.3), 0.3, role=ROLE_BLUE, fixed=True)
    return b.level()


def s_lander(sizes: SceneSizes = SIZE_S) -> Level:
    """A green pod high on the left with a thruster pushing up-right; a blue pad on the right of a red floor."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    craft = b.circle((0.8, 4.3), 0.2, role=ROLE_GREEN)
    b.thruster(craft, direction=math.radians(65.0), power=0.2)
    b.rect((3.9, GROUND + 0.15), 1.2, 0.3, role=ROLE_BLUE, fixed=True)
    return b.level()


def s_catapult(sizes: SceneSizes = SIZE_S) -> Level:
    """A motorised arm pinned to a point above the (red) floor, motor +1 swinging the loaded end up, holds a green
    ball; the blue ball floats on the right. (The arm's pivot is a joint to the floor polygon itself, which keeps
    both circles free for the ball and the goal.)"""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    pivot = (1.0, 1.0)
    arm = b.rect(pivot, 1.6, 0.12)
    b.hinge(arm, FLOOR, pivot, motor=True, speed=1.5, power=1.0, limits=(0.0, 1.2))
    b.circle((0.35, 1.06 + 0.15), 0.15, role=ROLE_GREEN)
    b.circle((4.3, 2.6), 0.35, role=ROLE_BLUE, fixed=True)
    return b.level()


# ---------------------------------------------------------------------------------------------------------------
# Size M: two polygons, three circles, two joints, two thrusters.


def m_car_bump(sizes: SceneSizes = SIZE_M) -> Level:
    """A two-wheel car with a green body (both wheels on motor binding 0), a bump, and a raised blue ball."""
    b = SceneBuilder(sizes)
    r, y = 0.2, GROUND + 0.2
    chassis = b.rect((0.9, y + 0.12), 1.3, 0.2, role=ROLE_GREEN)
    for x in (0.5, 1.3):
        wheel = b.circle((x, y), r)
        b.hinge(wheel, chassis, (x, y), motor=True, speed=1.5, power=1.0)
    b.polygon((2.5, GROUND + 0.1), _trapezoid(1.2, 0.4, 0.2), fixed=True)
    b.circle((4.6, 1.08), 0.3, role=ROLE_BLUE, fixed=True)
    return b.level()


def m_thrust_shelf(sizes: SceneSizes = SIZE_M) -> Level:
    """A green box with an up thruster (binding 0) and a right thruster (binding 1); the blue ball sits above a
    long red shelf, with a red ball overhead."""
    b = SceneBuilder(sizes)
    box = b.rect((0.6, GROUND + 0.2), 0.4, 0.4, role=ROLE_GREEN)
    b.thruster(box, direction=math.pi / 2, power=0.3, binding=0)
    b.thruster(box, direction=0.0, power=0.15, binding=1)
    b.rect((3.05, 2.1), 3.5, 0.16, role=ROLE_RED, fixed=True)
    b.circle((4.3, 2.6), 0.3, role=ROLE_BLUE, fixed=True)
    b.circle((3.0, 3.9), 0.35, role=ROLE_RED, fixed=True)
    return b.level()


def m_cartpole(sizes: SceneSizes = SIZE_M) -> Level:
    """A sliding cart pushed by thrusters (binding 0 right, 1 left) carries a free pole, slightly tilted, with a
    green ball on top; the blue ball is at pole height on the right, the floor red."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    x0 = 1.0
    cart = b.rect((x0, GROUND + 0.1), 0.6, 0.2, friction=0.0)
    base, length = (x0, GROUND + 0.2), 1.3
    _pole(b, cart, base, length, tilt=-0.04)
    b.thruster(cart, direction=0.0, power=0.6, binding=0)
    b.thruster(cart, direction=math.pi, power=0.6, binding=1)
    b.circle((4.4, base[1] + length), 0.2, role=ROLE_BLUE, fixed=True)
    return b.level()


def m_catapult(sizes: SceneSizes = SIZE_M) -> Level:
    """A motorised arm flings a green ball; the blue ledge is on the right, the floor red. Full power
    overshoots."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    pivot = (1.1, 1.0)
    arm = b.rect(pivot, 1.4, 0.12)
    hub = b.circle(pivot, 0.08, fixed=True)
    b.hinge(arm, hub, pivot, motor=True, speed=1.6, power=1.0, limits=(0.0, 1.1))
    b.circle((0.55, 1.06 + 0.15), 0.15, role=ROLE_GREEN)
    b.rect((3.9, 1.5), 1.0, 0.15, role=ROLE_BLUE, fixed=True)
    return b.level()


# ---------------------------------------------------------------------------------------------------------------
# Size L: eight polygons, four circles, six joints, two thrusters.


def l_car_climb(sizes: SceneSizes = SIZE_L) -> Level:
    """A two-wheel car with a green body, a ramp up to a ledge, a gap over the red floor, and the blue ball on
    the far plateau."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    r, y = 0.22, GROUND + 0.22
    chassis = b.rect((0.85, y + 0.14), 1.2, 0.2, role=ROLE_GREEN)
    for x in (0.45, 1.25):
        wheel = b.circle((x, y), r)
        b.hinge(wheel, chassis, (x, y), motor=True, speed=2.0, power=1.5)
    b.polygon((0.0, 0.0), [(1.6, GROUND), (3.0, 1.0), (3.0, GROUND)], fixed=True)
    b.rect((4.2, (GROUND + 1.0) / 2), 1.6, 1.0 - GROUND, fixed=True)
    b.circle((4.65, 1.6), 0.3, role=ROLE_BLUE, fixed=True)
    return b.level()


def l_lander(sizes: SceneSizes = SIZE_L) -> Level:
    """A green craft with two welded legs and two jets (binding 0 up-right, 1 up-left) high on the left; a red
    tower, a red floor and a blue pad on the right."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    cx, cy = 0.8, 4.2
    body = b.rect((cx, cy), 0.5, 0.25, role=ROLE_GREEN)
    for side in (-1, 1):
        foot, hip = (cx + side * 0.3, cy - 0.3), (cx + side * 0.2, cy - 0.12)
        mid = ((foot[0] + hip[0]) / 2, (foot[1] + hip[1]) / 2)
        angle = math.atan2(foot[1] - hip[1], foot[0] - hip[0]) + math.pi / 2
        leg = b.rect(mid, 0.05, math.dist(foot, hip), rotation=angle, role=ROLE_GREEN, density=0.5)
        b.weld(body, leg, hip)
    b.thruster(body, direction=math.radians(60.0), power=0.18, binding=0)
    b.thruster(body, direction=math.radians(120.0), power=0.18, binding=1)
    b.rect((2.3, (GROUND + 2.6) / 2), 0.3, 2.6 - GROUND, role=ROLE_RED, fixed=True)
    b.rect((3.9, GROUND + 0.1), 1.0, 0.2, role=ROLE_BLUE, fixed=True)
    return b.level()


def l_cartpole(sizes: SceneSizes = SIZE_L) -> Level:
    """A cart on two motorised wheels (+1 rolls right) carries a free pole, slightly tilted, with a green ball on
    top; the blue ball is at pole height on the right, the floor red."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    x0, r = 1.0, 0.15
    axle = GROUND + r
    cart = b.rect((x0, axle + 0.05), 0.7, 0.15)
    for dx in (-0.25, 0.25):
        wheel = b.circle((x0 + dx, axle), r)
        b.hinge(wheel, cart, (x0 + dx, axle), motor=True, speed=1.5, power=1.0)
    base, length = (x0, axle + 0.125), 1.3
    _pole(b, cart, base, length, tilt=-0.03)
    b.circle((4.3, base[1] + length), 0.2, role=ROLE_BLUE, fixed=True)
    return b.level()


def l_catapult(sizes: SceneSizes = SIZE_L) -> Level:
    """A motorised arm with a lip holds a green ball; a red wall stands between it and the blue ledge, the floor
    is red. A short swing falls into the wall."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    pivot, left, right, y = (1.3, 1.1), 0.4, 1.5, 1.1
    arm = b.rect(((left + right) / 2, y), right - left, 0.1)
    hub = b.circle(pivot, 0.08, fixed=True)
    b.hinge(arm, hub, pivot, motor=True, speed=2.4, power=0.8, limits=(0.0, 0.6))
    lip = b.rect((left + 0.03, y + 0.1), 0.06, 0.2)
    b.weld(arm, lip, (left + 0.03, y + 0.05))
    b.circle((left + 0.21, y + 0.05 + 0.15), 0.15, role=ROLE_GREEN)
    b.rect((3.0, (GROUND + 2.2) / 2), 0.2, 2.2 - GROUND, role=ROLE_RED, fixed=True)
    b.rect((3.9, 1.6), 0.8, 0.15, role=ROLE_BLUE, fixed=True)
    return b.level()


def l_claw(sizes: SceneSizes = SIZE_L) -> Level:
    """An arm on a fixed hub (binding 0, +1 swings it up and over) ends in a two-finger claw (binding 1, +1
    closes, -1 opens) around a green ball on a thin post; the blue bin is on the right, the floor red."""
    b = SceneBuilder(sizes)
    b.role(FLOOR, ROLE_RED)
    hub_at = (2.5, 2.4)
    palm_x, palm_y = 1.2, hub_at[1]
    ball_y = palm_y - 0.35
    arm = b.rect(((0.9 + hub_at[0]) / 2, palm_y + 0.05), hub_at[0] - 0.9, 0.1)
    hub = b.circle(hub_at, 0.08, fixed=True)
    b.hinge(arm, hub, hub_at, motor=True, speed=0.3, power=2.0, binding=0, limits=(0.0, math.pi + 0.8))
    # Fingers with inward hooks, each hinged above its centre of mass so it hangs open at rest; closing them cages
    # the ball between the hooks and the palm, opening them wide lets it roll out.
    top, bottom = palm_y, ball_y - 0.17
    for side in (-1, 1):
        xs = [palm_x + side * 0.31, palm_x + side * 0.25, palm_x + side * 0.18, palm_x + side * 0.31]
        ys = [top, top, bottom, bottom]
        if side > 0:  # mirrored: reverse to keep the vertices clockwise
            xs, ys = xs[::-1], ys[::-1]
        finger = b.polygon((0.0, 0.0), list(zip(xs, ys)))
        hinge_at = (float(b.state.bodies.position[finger][0]), top)
        a, c = (arm, finger) if side < 0 else (finger, arm)
        b.hinge(a, c, hinge_at, motor=True, speed=0.5, power=1.0, binding=1, limits=(-1.3, 0.25))
    b.rect((palm_x, (GROUND + ball_y - 0.15) / 2), 0.06, ball_y - 0.15 - GROUND, fixed=True)
    b.circle((palm_x, ball_y), 0.15, role=ROLE_GREEN, density=0.5)
    b.rect((4.3, (GROUND + 1.0) / 2), 1.0, 1.0 - GROUND, role=ROLE_BLUE, fixed=True)
    return b.level()
