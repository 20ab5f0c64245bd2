"""`engine.levels.checks.unsolvable_reasons`: each reason a level certainly cannot be solved (no green, no blue, no
pair the engine tests, everything fixed in place and apart), and none for levels that can be, all on small levels
edited in numpy from one S scene (one compile)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from impulse.engine.levels.checks import NO_BLUE, NO_GREEN, TOUCH_MARGIN, unsolvable_reasons
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_NEUTRAL, Level
from impulse.engine.physics.sizes import SIZE_S, SceneSizes
from tests.support.monitor_scenes import GREEN_AT, small_level

BOX, BLUE, RED = 4, 5, 6  # the small level's green box, blue (fixed) ball and red ball
FLOOR, LEFT_WALL = 0, 1
FIXED = "every green and blue shape is fixed in place and apart: nothing can move them together"


@pytest.fixture(scope="module")
def base() -> Level:
    return small_level()


def edited(level: Level, roles: dict[int, int] | None = None, **bodies: dict[int, object]) -> Level:
    """`level` with some roles and body fields changed: `edited(level, {4: 0}, inverse_mass={4: 0.0})`."""
    new_roles = np.array(level.roles)
    for body, role in (roles or {}).items():
        new_roles[body] = role
    fields = {}
    for field, values in bodies.items():
        column = np.array(getattr(level.state.bodies, field))
        for body, value in values.items():
            column[body] = value
        fields[field] = column
    state = level.state.replace(bodies=level.state.bodies.replace(**fields))
    return level.replace(roles=new_roles, state=state)


def with_radius(level: Level, body: int, radius: float) -> Level:
    radii = np.array(level.state.circle_radius)
    radii[body - SIZE_S.num_polygons] = radius
    return level.replace(state=level.state.replace(circle_radius=radii))


def test_a_level_with_a_movable_green_and_a_blue_can_be_solved(base: Level) -> None:
    assert unsolvable_reasons(base, SIZE_S) == []
    assert unsolvable_reasons(jax.tree.map(np.asarray, base), SIZE_S) == []


def test_missing_roles_and_inactive_shapes(base: Level) -> None:
    assert unsolvable_reasons(edited(base, {BOX: ROLE_NEUTRAL}), SIZE_S) == [NO_GREEN]
    assert unsolvable_reasons(edited(base, {BLUE: ROLE_NEUTRAL}), SIZE_S) == [NO_BLUE]
    assert unsolvable_reasons(edited(base, {BOX: ROLE_BLUE, BLUE: ROLE_GREEN, RED: ROLE_NEUTRAL}), SIZE_S) == []
    assert unsolvable_reasons(edited(base, {BOX: ROLE_NEUTRAL, BLUE: ROLE_NEUTRAL}), SIZE_S) == [NO_GREEN, NO_BLUE]
    assert unsolvable_reasons(edited(base, active={BOX: False}), SIZE_S) == [NO_GREEN]  # an unused slot is no shape


def test_collision_modes_and_the_arena(base: Level) -> None:
    reasons = unsolvable_reasons(edited(base, collision_mode={BOX: 0, BLUE: 1}), SIZE_S)
    assert len(reasons) == 1 and "collision modes never meet" in reasons[0], reasons
    assert unsolvable_reasons(edited(base, collision_mode={BOX: 0, BLUE: 2}), SIZE_S) == []
    # A green floor and a blue wall, and nothing else green or blue: the arena is never tested against itself.
    arena_only = edited(base, {BOX: ROLE_NEUTRAL, BLUE: ROLE_NEUTRAL, FLOOR: ROLE_GREEN, LEFT_WALL: ROLE_BLUE})
    [reason] = unsolvable_reasons(arena_only, SIZE_S)
    assert reason.startswith("no green shape can ever touch a blue one: the arena polygons"), reason
    # A green floor and the blue ball can touch, but both are fixed and apart; a falling blue box can reach it.
    assert unsolvable_reasons(edited(base, {BOX: ROLE_NEUTRAL, FLOOR: ROLE_GREEN}), SIZE_S) == [FIXED]
    assert unsolvable_reasons(edited(base, {BOX: ROLE_BLUE, BLUE: ROLE_NEUTRAL, FLOOR: ROLE_GREEN}), SIZE_S) == []


def test_fixed_shapes_apart_or_touching(base: Level) -> None:
    fixed_green = edited(base, inverse_mass={BOX: 0.0}, inverse_inertia={BOX: 0.0})
    assert unsolvable_reasons(fixed_green, SIZE_S) == [FIXED]
    # A fixed body that is given a velocity or a spin drifts (fixed bodies keep their velocity): it may get there.
    assert unsolvable_reasons(edited(fixed_green, velocity={BOX: (0.5, 0.0)}), SIZE_S) == []
    assert unsolvable_reasons(edited(fixed_green, angular_velocity={BOX: 1.0}), SIZE_S) == []
    # The box is 0.8 x 0.6 m: a fixed blue ball of radius 0.1 just beyond its right face touches it or not.
    x, y = GREEN_AT
    near = with_radius(fixed_green, BLUE, 0.1)
    assert unsolvable_reasons(edited(near, position={BLUE: (x + 0.4 + 0.1 + 2 * TOUCH_MARGIN, y)}), SIZE_S) == [FIXED]
    assert unsolvable_reasons(edited(near, position={BLUE: (x + 0.4 + 0.1 - 0.01, y)}), SIZE_S) == []
    assert unsolvable_reasons(edited(near, position={BLUE: (x, y)}), SIZE_S) == []  # its centre inside the box
    # Above the box: 0.05 m clear of its top face (half-height 0.3), but turned by 90 degrees (half-height 0.4)
    # the box reaches into the ball.
    above = edited(near, position={BLUE: (x, y + 0.3 + 0.1 + 0.05)})
    assert unsolvable_reasons(above, SIZE_S) == [FIXED]
    assert unsolvable_reasons(edited(above, rotation={BOX: np.pi / 2}), SIZE_S) == []
    # Two fixed balls (the red one turned blue, the blue one green): apart, then overlapping.
    balls = edited(base, {BOX: ROLE_NEUTRAL, BLUE: ROLE_GREEN, RED: ROLE_BLUE}, inverse_mass={RED: 0.0},
                   inverse_inertia={RED: 0.0})
    assert unsolvable_reasons(balls, SIZE_S) == [FIXED]
    blue_at = np.asarray(base.state.bodies.position)[BLUE]
    assert unsolvable_reasons(edited(balls, position={RED: blue_at + (0.45, 0.0)}), SIZE_S) == []


def test_a_fixed_polygon_resting_on_a_green_floor(base: Level) -> None:
    """Polygon against polygon (the separating-axis test): a fixed blue box just above the green floor, then
    resting on it."""
    floor = np.asarray(base.state.polygon_vertices)[FLOOR] + np.asarray(base.state.bodies.position)[FLOOR]
    top = float(floor[:, 1].max())  # the floor is not rotated
    on_floor = edited(base, {FLOOR: ROLE_GREEN, BOX: ROLE_BLUE, BLUE: ROLE_NEUTRAL}, inverse_mass={BOX: 0.0},
                      inverse_inertia={BOX: 0.0})
    assert unsolvable_reasons(edited(on_floor, position={BOX: (2.0, top + 0.3 + 0.1)}), SIZE_S) == [FIXED]
    assert unsolvable_reasons(edited(on_floor, position={BOX: (2.0, top + 0.3 - 1e-4)}), SIZE_S) == []


def test_a_batch_or_another_size_is_refused(base: Level) -> None:
    batch = jax.tree.map(lambda x: np.stack([x, x]), jax.tree.map(np.asarray, base))
    with pytest.raises(ValueError, match="one level"):
        unsolvable_reasons(batch, SIZE_S)
    with pytest.raises(ValueError, match="one level"):
        unsolvable_reasons(base, SceneSizes(num_polygons=6))
