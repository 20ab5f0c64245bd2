"""Checks that a scene is one the engine can simulate meaningfully, with messages that name the slot and field.

Runs on concrete (host) arrays of a single scene, outside jit: it is for level files, editors and tests, not for
the hot path.
"""

from __future__ import annotations

import numpy as np

from impulse.engine.physics.building import arena_polygon_count, connected_by_joints
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState

_MIN_EDGE = 1e-4
_MIN_RADIUS = 1e-4


class SceneError(ValueError):
    """A scene failed validation; `problems` lists every problem found."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("invalid scene:\n  " + "\n  ".join(problems))


def scene_sizes_of(state: SimState) -> SceneSizes:
    return SceneSizes(
        num_polygons=state.polygon_vertices.shape[0],
        num_circles=state.circle_radius.shape[0],
        num_joints=state.joints.active.shape[0],
        num_thrusters=state.thrusters.active.shape[0],
        max_polygon_vertices=state.polygon_vertices.shape[1],
        num_static_polygons=arena_polygon_count(state),
    )


def _non_finite(state: SimState) -> list[str]:
    problems = []
    for group_name, group in (
        ("bodies", state.bodies),
        ("joints", state.joints),
        ("thrusters", state.thrusters),
        ("contacts", state.contacts),
    ):
        for field, value in vars(group).items():
            arr = np.asarray(value)
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                slots = sorted({int(i) for i in np.argwhere(~np.isfinite(arr))[:, 0]})
                problems.append(f"{group_name}.{field}: NaN or infinite value in slot(s) {slots}")
    for field in ("polygon_vertices", "circle_radius", "gravity"):
        arr = np.asarray(getattr(state, field))
        if not np.all(np.isfinite(arr)):
            problems.append(f"{field}: NaN or infinite value")
    return problems


def _polygons(state: SimState) -> list[str]:
    problems = []
    active = np.asarray(state.bodies.active)
    vertices = np.asarray(state.polygon_vertices, dtype=np.float64)
    counts = np.asarray(state.polygon_n_vertices)
    max_vertices = vertices.shape[1]
    for p in range(vertices.shape[0]):
        if not active[p]:
            continue
        n = int(counts[p])
        if not 3 <= n <= max_vertices:
            problems.append(f"polygon {p}: has {n} vertices; polygons need 3 to {max_vertices}")
            continue
        v = vertices[p, :n]
        edges = np.roll(v, -1, axis=0) - v
        if np.min(np.linalg.norm(edges, axis=1)) < _MIN_EDGE:
            problems.append(f"polygon {p}: zero-size (an edge is shorter than {_MIN_EDGE} m)")
            continue
        turn = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
        if np.all(turn > 0):
            problems.append(f"polygon {p}: vertices are counter-clockwise; the engine needs clockwise order")
        elif not np.all(turn < 0):
            problems.append(f"polygon {p}: not convex (or has collinear vertices)")
    return problems


def _bodies(state: SimState, sizes: SceneSizes) -> list[str]:
    problems = []
    b = state.bodies
    active = np.asarray(b.active)
    for field in ("inverse_mass", "inverse_inertia", "friction", "restitution"):
        values = np.asarray(getattr(b, field))
        bad = np.flatnonzero(active & (values < 0))
        if bad.size:
            problems.append(f"bodies.{field}: negative in body slot(s) {bad.tolist()}")
    modes = np.asarray(b.collision_mode)
    bad = np.flatnonzero(active & ~np.isin(modes, (0, 1, 2)))
    if bad.size:
        problems.append(f"bodies.collision_mode: must be 0, 1 or 2 (body slot(s) {bad.tolist()})")
    radius = np.asarray(state.circle_radius)
    circle_active = active[sizes.num_polygons :]
    bad = np.flatnonzero(circle_active & (radius < _MIN_RADIUS))
    if bad.size:
        problems.append(f"circle(s) {bad.tolist()}: zero-size (radius below {_MIN_RADIUS} m)")
    return problems


def _links(state: SimState, sizes: SceneSizes) -> list[str]:
    problems = []
    n = sizes.num_bodies
    active = np.asarray(state.bodies.active)
    j = state.joints
    for slot in np.flatnonzero(np.asarray(j.active)):
        a, b = int(np.asarray(j.a_index)[slot]), int(np.asarray(j.b_index)[slot])
        if not (0 <= a < n and 0 <= b < n):
            problems.append(f"joint {slot}: body index out of range (a={a}, b={b}, bodies 0..{n - 1})")
        elif a == b:
            problems.append(f"joint {slot}: joins body {a} to itself")
        elif not (active[a] and active[b]):
            problems.append(f"joint {slot}: joins an inactive body (a={a}, b={b})")
        if np.asarray(j.motor_has_joint_limits)[slot] and np.asarray(j.min_rotation)[slot] > np.asarray(
            j.max_rotation
        )[slot]:
            problems.append(f"joint {slot}: min_rotation is greater than max_rotation")
    t = state.thrusters
    for slot in np.flatnonzero(np.asarray(t.active)):
        body = int(np.asarray(t.body_index)[slot])
        if not 0 <= body < n:
            problems.append(f"thruster {slot}: body index {body} out of range (bodies 0..{n - 1})")
        elif not active[body]:
            problems.append(f"thruster {slot}: attached to inactive body {body}")
    if not problems:
        tables = pair_tables(sizes)
        expected = ~np.asarray(connected_by_joints(state.joints, n))[tables.pair_a, tables.pair_b]
        if not np.array_equal(expected, np.asarray(state.pair_collides)):
            problems.append("pair_collides: stale collision filter; call refresh_collision_filter after editing joints")
    return problems


def validate_scene(state: SimState) -> list[str]:
    """Every problem found in a single (unbatched) scene; an empty list means the scene is valid."""
    if np.ndim(state.bodies.rotation) != 1:
        return [f"expected one scene, got a batch of shape {np.shape(state.bodies.rotation)[:-1]}"]
    sizes = scene_sizes_of(state)
    problems = _non_finite(state)
    problems += _polygons(state)
    problems += _bodies(state, sizes)
    problems += _links(state, sizes)
    return problems


def check_scene(state: SimState) -> SimState:
    """Raise SceneError listing every problem, or return the scene unchanged."""
    problems = validate_scene(state)
    if problems:
        raise SceneError(problems)
    return state
