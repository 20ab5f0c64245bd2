"""Checks of a level's task that scene validation does not make: whether the level can be solved at all.

A level is solved when a green shape touches a blue one (Kinetix's success: an active contact between a green and a
blue shape; the Kinetix digest, section 5.2). `unsolvable_reasons` lists why a level certainly cannot be solved, one
short phrase per reason, so that `impulse levels validate` (and the studio, when a level is saved) can warn about a
level that is valid as a scene but pointless as a task. An empty list means that none of these was found, not that
the level is solvable: only playing it can tell that.

What is checked, in this order, on the level's start (only active shapes count, as in Kinetix's reward):

1. "no green shape": no active shape has the green role.
2. "no blue shape": likewise for blue (1 and 2 may both be reported; then nothing else is checked).
3. No green and blue shape can ever touch, because for every (green, blue) pair either
   - both are arena polygons (the first `num_static_polygons` polygons): the engine never tests the arena against
     itself, or
   - their collision modes never meet (`engine.physics.narrowphase.modes_collide`: mode 0 meets only mode 2).
4. Nothing can move them together: every green and blue shape of the pairs that can touch is fixed in place, and no
   such pair touches at the start. Fixed in place means inverse mass 0 and at rest (no velocity, no spin): gravity,
   contacts, joints, motors and thrusters all act through the inverse mass, so such a body never moves (a fixed
   body that is given a velocity does drift, and is not counted as fixed). Touching at the start is decided with a
   margin of `TOUCH_MARGIN`: a pair whose outlines are closer than that may touch (the level is then solved, or
   failed, on its first step) and is not reported.

Not detected (they would need the physics): a dynamic shape that its joints hold in place, a blue shape out of any
reach, a green shape that touches red before it can reach blue.
"""

from __future__ import annotations

import numpy as np

from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, Level, level_sizes
from impulse.engine.physics.sizes import SceneSizes

TOUCH_MARGIN = 1e-3
"""Metres: shapes whose outlines are closer than this at the start are taken to be possibly touching."""

NO_GREEN = "no green shape"
NO_BLUE = "no blue shape"


def unsolvable_reasons(level: Level, sizes: SceneSizes) -> list[str]:
    """Why the (unbatched) `level` of slot counts `sizes` certainly cannot be solved (the module docstring lists
    the cases); empty when no such reason was found. Host side, numpy; raises ValueError for a batch of levels or a
    level of other sizes."""
    bodies = level.state.bodies
    active = np.asarray(bodies.active, bool)
    if active.ndim != 1 or not level_sizes(level, sizes):
        raise ValueError(f"unsolvable_reasons takes one level of {sizes}, got arrays of shape {active.shape}")
    roles = np.asarray(level.roles)
    green = np.flatnonzero(active & (roles == ROLE_GREEN))
    blue = np.flatnonzero(active & (roles == ROLE_BLUE))
    reasons = [reason for reason, shapes in ((NO_GREEN, green), (NO_BLUE, blue)) if shapes.size == 0]
    if reasons:
        return reasons

    modes = np.asarray(bodies.collision_mode)
    arena = np.arange(active.size) < sizes.num_static_polygons
    pairs = [(int(g), int(b)) for g in green for b in blue]
    both_arena = {pair for pair in pairs if arena[pair[0]] and arena[pair[1]]}
    modes_apart = {pair for pair in pairs if not _modes_collide(int(modes[pair[0]]), int(modes[pair[1]]))}
    possible = [pair for pair in pairs if pair not in both_arena and pair not in modes_apart]
    if not possible:
        why = []
        if both_arena:
            why.append("the arena polygons are never tested against each other")
        if modes_apart:
            why.append("their collision modes never meet (mode 0 meets only mode 2)")
        return [f"no green shape can ever touch a blue one: {'; '.join(why)}"]

    moves = ((np.asarray(bodies.inverse_mass) != 0) | np.any(np.asarray(bodies.velocity) != 0, axis=-1)
             | (np.asarray(bodies.angular_velocity) != 0))
    if any(moves[g] or moves[b] for g, b in possible):
        return []
    outlines = _Outlines(level, sizes)
    if any(not outlines.apart(g, b) for g, b in possible):
        return []
    return ["every green and blue shape is fixed in place and apart: nothing can move them together"]


def _modes_collide(mode_a: int, mode_b: int) -> bool:
    """The engine's collision-mode test (`engine.physics.narrowphase.modes_collide`) for two shapes."""
    return mode_a == 2 or mode_b == 2 or mode_a * mode_b > 0


class _Outlines:
    """The shapes of one level in the world frame: polygons as vertex lists, circles as centre and radius."""

    def __init__(self, level: Level, sizes: SceneSizes):
        state = level.state
        self.num_polygons = sizes.num_polygons
        self.position = np.asarray(state.bodies.position, np.float64)
        self.rotation = np.asarray(state.bodies.rotation, np.float64)
        self.vertices = np.asarray(state.polygon_vertices, np.float64)
        self.n_vertices = np.asarray(state.polygon_n_vertices)
        self.radius = np.asarray(state.circle_radius, np.float64)

    def polygon(self, body: int) -> np.ndarray:
        """[n, 2] world vertices of polygon `body`."""
        local = self.vertices[body, : int(self.n_vertices[body])]
        c, s = np.cos(self.rotation[body]), np.sin(self.rotation[body])
        return self.position[body] + local @ np.array([[c, s], [-s, c]])

    def apart(self, a: int, b: int) -> bool:
        """Whether shapes `a` and `b` are certainly further apart than TOUCH_MARGIN (never for a polygon of fewer
        than 3 vertices, which only an invalid scene has)."""
        P = self.num_polygons
        if any(body < P and self.n_vertices[body] < 3 for body in (a, b)):
            return False
        if a >= P and b >= P:
            gap = np.linalg.norm(self.position[a] - self.position[b]) - self.radius[a - P] - self.radius[b - P]
            return bool(gap > TOUCH_MARGIN)
        if a >= P or b >= P:
            circle, polygon = (a, b) if a >= P else (b, a)
            gap = _point_polygon_distance(self.position[circle], self.polygon(polygon)) - self.radius[circle - P]
            return bool(gap > TOUCH_MARGIN)
        return _separation(self.polygon(a), self.polygon(b)) > TOUCH_MARGIN


def _outward_normals(vertices: np.ndarray) -> np.ndarray:
    """[n, 2] unit normals of a convex polygon's edges (vertex i to i + 1), pointing away from it whatever the
    winding; a zero-length edge gets a zero normal."""
    edges = np.roll(vertices, -1, axis=0) - vertices
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=-1)
    lengths = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.where(lengths > 0, normals / np.where(lengths > 0, lengths, 1.0), 0.0)
    midpoints = vertices + edges / 2
    inward = np.einsum("ij,ij->i", normals, midpoints - vertices.mean(axis=0)) < 0
    return np.where(inward[:, None], -normals, normals)


def _separation(a: np.ndarray, b: np.ndarray) -> float:
    """The largest gap between two convex polygons along either one's edge normals (the separating-axis test): a
    lower bound of their distance, negative when they overlap."""
    gaps = []
    for one, other in ((a, b), (b, a)):
        normals = _outward_normals(one)
        # For each edge of `one`: how far the nearest vertex of `other` lies beyond it.
        gaps.append((np.einsum("jk,ik->ij", other, normals) - np.einsum("ik,ik->i", one, normals)[:, None]).min(-1))
    return float(np.concatenate(gaps).max())


def _point_polygon_distance(point: np.ndarray, vertices: np.ndarray) -> float:
    """The distance from `point` to a convex polygon (0 inside it)."""
    normals = _outward_normals(vertices)
    if np.all(np.einsum("ik,ik->i", point - vertices, normals) <= 0):
        return 0.0
    start, edge = vertices, np.roll(vertices, -1, axis=0) - vertices
    along = np.clip(np.einsum("ik,ik->i", point - start, edge) / np.maximum(np.einsum("ik,ik->i", edge, edge),
                                                                             1e-18), 0.0, 1.0)
    return float(np.linalg.norm(start + along[:, None] * edge - point, axis=-1).min())
