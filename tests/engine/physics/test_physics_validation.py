"""The scene validator, and the Kinetix level files (loaded, validated, stepped)."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.physics import (
    SceneError,
    add_circle,
    add_polygon,
    add_rectangle,
    add_revolute_joint,
    add_thruster,
    check_scene,
    validate_scene,
)
from tests.support.paths import SHARED_LEVELS
from tests.support.physics_sim import SIZES, arena_scene, non_finite_leaves, run, set_body_field

LEVELS = SHARED_LEVELS


def _valid_scene():
    state = arena_scene()
    state, box = add_rectangle(state, (2.0, 1.0), 0.5, 0.5)
    state, ball = add_circle(state, (3.0, 1.0), 0.2)
    state, _ = add_revolute_joint(state, box, ball, (0.5, 0.0), (-0.5, 0.0))
    state, _ = add_thruster(state, box, (0.0, 0.0), 0.0, 1.0)
    return state


def _one_problem(state) -> str:
    problems = validate_scene(state)
    assert len(problems) == 1, problems
    return problems[0]


def test_valid_scene_has_no_problems():
    state = _valid_scene()
    assert validate_scene(state) == []
    assert check_scene(state) is state


def test_counter_clockwise_polygon():
    ccw = np.array([[-0.2, -0.2], [0.2, -0.2], [0.2, 0.2], [-0.2, 0.2]])
    state, index = add_polygon(arena_scene(), (2.0, 1.0), ccw)
    message = _one_problem(state)
    assert "counter-clockwise" in message and f"polygon {int(index)}" in message


def test_non_convex_quad():
    # Clockwise dart: the second vertex is a reflex corner.
    dart = np.array([[-0.3, 0.3], [0.0, 0.0], [0.3, 0.3], [0.0, -0.3]])
    state, index = add_polygon(arena_scene(), (2.0, 1.0), dart)
    message = _one_problem(state)
    assert "convex" in message and "counter-clockwise" not in message and f"polygon {int(index)}" in message


def test_nan_position():
    state = set_body_field(_valid_scene(), "position", 4, jnp.array([np.nan, 1.0]))
    message = _one_problem(state)
    assert "NaN" in message and "position" in message and "[4]" in message


def test_zero_size_circle():
    state, _ = add_circle(arena_scene(), (2.0, 1.0), 0.0)
    message = _one_problem(state)
    assert "zero-size" in message and "circle" in message


def test_joint_index_out_of_range():
    state = _valid_scene()
    state = state.replace(joints=state.joints.replace(b_index=state.joints.b_index.at[0].set(99)))
    message = _one_problem(state)
    assert "out of range" in message and "joint 0" in message and "99" in message


def test_thruster_index_out_of_range():
    state = _valid_scene()
    state = state.replace(
        thrusters=state.thrusters.replace(body_index=state.thrusters.body_index.at[0].set(-3))
    )
    message = _one_problem(state)
    assert "out of range" in message and "thruster 0" in message


def test_check_scene_raises_with_every_problem():
    ccw = np.array([[-0.2, -0.2], [0.2, -0.2], [0.2, 0.2], [-0.2, 0.2]])
    state, _ = add_polygon(arena_scene(), (2.0, 1.0), ccw)
    state, _ = add_circle(state, (3.0, 1.0), 0.0)
    with pytest.raises(SceneError) as caught:
        check_scene(state)
    assert len(caught.value.problems) == 2
    assert "counter-clockwise" in str(caught.value) and "zero-size" in str(caught.value)


def _level_files() -> list[Path]:
    if not LEVELS.is_dir():
        pytest.skip(
            f"Kinetix level files not found at {LEVELS.resolve()} (the shared folder beside the checkout)"
        )
    files = sorted(LEVELS.rglob("*.json"))
    if not files:
        pytest.skip(f"no .json level files under {LEVELS.resolve()}")
    return files


def test_kinetix_levels_load_and_validate():
    from impulse.engine.levels.kinetix_json import load_kinetix_level

    problems = {}
    for path in _level_files():
        level = load_kinetix_level(path)
        found = validate_scene(level.state)
        if found:
            problems[str(path.relative_to(LEVELS))] = found
    assert not problems, problems


def test_kinetix_small_level_runs_without_nan():
    from impulse.engine.levels.kinetix_json import load_kinetix_level

    small = [p for p in _level_files() if p.parent.name == "s"]
    if not small:
        pytest.skip(f"no S levels under {LEVELS.resolve()}")
    # The one-wheel car has a motorised joint; fall back to any S level.
    path = next((p for p in small if p.name == "h2_one_wheel_car.json"), small[0])
    level = load_kinetix_level(path)
    assert level.sizes.fits_in(SIZES)
    actions = jnp.zeros((120, level.sizes.num_joints + level.sizes.num_thrusters), jnp.float32)
    final, records = run(level.state, level.params, actions, level.sizes)
    assert not non_finite_leaves(final), f"{path.name}: {non_finite_leaves(final)}"
    position = np.asarray(records[0])
    assert np.isfinite(position).all()
    # Nothing leaves the arena in two seconds without actions (some slack for shapes resting against a wall).
    movable = np.array(level.state.bodies.active)
    movable[: level.sizes.num_static_polygons] = False
    worst = np.abs(position[:, movable] - 2.5).max()
    assert worst < 3.0, (
        f"{path.name}: a body got {worst:.2f} m away from the arena centre (2.5, 2.5) in x or y"
    )
