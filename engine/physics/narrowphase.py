"""Contact detection for every pair slot of one scene, all pairs in parallel.

Conventions follow Jax2D so that contacts (and the Kinetix reward built on them) agree: normals point from body a
to body b; polygon pairs use separating axes with a 0.01 m preference for a's face, clamp-style clipping onto the
reference face, the deeper point first, and one shared penetration; a circle centre inside a polygon reports the
radius as penetration. Polygons are transformed to the world once per step, not once per pair.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from impulse.engine.physics.geometry import cross, dot, nonzero, rotate
from impulse.engine.physics.pairs import PairTables
from impulse.engine.physics.state import SimState

Array = jnp.ndarray

# A polygon pair prefers a's face as reference unless b's separation is larger by this much (Jax2D's rule).
REFERENCE_FACE_TOLERANCE = 0.01
_FAR = 1e9


class Contacts(NamedTuple):
    """One entry per contact slot (see pairs.py for the slot order)."""

    touching: Array  # [K] bool: geometric overlap, before joint filtering
    normal: Array  # [K, 2] from a towards b
    point: Array  # [K, 2] world
    penetration: Array  # [K]


def modes_collide(mode_a: Array, mode_b: Array) -> Array:
    return (mode_a == 2) | (mode_b == 2) | (mode_a * mode_b > 0)


class _Polygons(NamedTuple):
    vertices: Array  # [P, V, 2] world
    next_vertices: Array  # [P, V, 2] world, the end of each edge
    normals: Array  # [P, V, 2] world outward unit normals
    valid: Array  # [P, V] bool: vertex/edge exists


def _world_polygons(state: SimState) -> _Polygons:
    num_polygons, max_vertices = state.polygon_vertices.shape[:2]
    pos = state.bodies.position[:num_polygons]
    rot = state.bodies.rotation[:num_polygons]
    local = state.polygon_vertices
    n = state.polygon_n_vertices[:, None]
    k = jnp.arange(max_vertices)[None, :]
    valid = k < n
    next_index = jnp.where(k + 1 < n, k + 1, 0)
    local_next = jnp.take_along_axis(local, next_index[..., None], axis=1)
    world = pos[:, None, :] + rotate(rot[:, None], local)
    world_next = pos[:, None, :] + rotate(rot[:, None], local_next)
    edge = world_next - world
    # Clockwise winding: rotating an edge by +90 degrees gives the outward normal.
    outward = jnp.stack([-edge[..., 1], edge[..., 0]], axis=-1)
    outward = outward / nonzero(jnp.sqrt(dot(outward, outward)))[..., None]
    return _Polygons(world, world_next, outward, valid)


def _best_axis(ref: _Polygons, inc: _Polygons) -> tuple[Array, Array, Array, Array]:
    """Separating-axis search over ref's faces for each pair; returns (separation, face, deepest, second)."""
    # offsets[p, face, vertex] = normal_face . (inc_vertex - ref_face_start); [n, V, V]
    rel = inc.vertices[:, None, :, :] - ref.vertices[:, :, None, :]
    proj = dot(ref.normals[:, :, None, :], rel)
    proj = jnp.where(inc.valid[:, None, :], proj, _FAR)
    separation = jnp.where(ref.valid, proj.min(axis=-1), -_FAR)
    face = jnp.argmax(separation, axis=-1)
    best_sep = jnp.take_along_axis(separation, face[:, None], axis=1)[:, 0]
    depth = jnp.take_along_axis(proj, face[:, None, None], axis=1)[:, 0]
    first = jnp.argmin(depth, axis=-1)
    depth_without_first = jnp.where(jnp.arange(depth.shape[-1])[None] == first[:, None], _FAR * 2, depth)
    second = jnp.argmin(depth_without_first, axis=-1)
    take = lambda verts, i: jnp.take_along_axis(verts, i[:, None, None], axis=1)[:, 0]  # noqa: E731
    return best_sep, face, take(inc.vertices, first), take(inc.vertices, second)


def _face(polys: _Polygons, face: Array) -> tuple[Array, Array, Array]:
    take = lambda arr: jnp.take_along_axis(arr, face[:, None, None], axis=1)[:, 0]  # noqa: E731
    return take(polys.vertices), take(polys.next_vertices), take(polys.normals)


def _polygon_polygon(state: SimState, tables: PairTables) -> tuple[Contacts, Contacts]:
    world = _world_polygons(state)
    gather = lambda polys, idx: _Polygons(*(x[idx] for x in polys))  # noqa: E731
    a, b = gather(world, tables.rr_a), gather(world, tables.rr_b)
    sep_a, face_a, deep_b1, deep_b2 = _best_axis(a, b)
    sep_b, face_b, deep_a1, deep_a2 = _best_axis(b, a)
    b_is_reference = sep_a + REFERENCE_FACE_TOLERANCE < sep_b

    a_start, a_end, a_normal = _face(a, face_a)
    b_start, b_end, b_normal = _face(b, face_b)
    pick = lambda x_if_b, x_if_a: jnp.where(b_is_reference[:, None], x_if_b, x_if_a)  # noqa: E731
    start, end, ref_normal = pick(b_start, a_start), pick(b_end, a_end), pick(b_normal, a_normal)
    incident1, incident2 = pick(deep_a1, deep_b1), pick(deep_a2, deep_b2)
    normal = pick(-b_normal, a_normal)

    edge = end - start
    edge_length = jnp.sqrt(dot(edge, edge))
    along = edge / nonzero(edge_length)[:, None]

    def clip(point: Array) -> tuple[Array, Array]:
        # depth > 0 means the point lies behind the reference face (inside the reference body).
        offset = point - start
        depth = -dot(offset, ref_normal)
        slide = jnp.clip(dot(offset, along), 0.0, edge_length)
        return start + slide[:, None] * along - depth[:, None] * ref_normal, depth

    p1, depth1 = clip(incident1)
    p2, depth2 = clip(incident2)
    first_deeper = depth1 >= depth2
    point0 = jnp.where(first_deeper[:, None], p1, p2)
    point1 = jnp.where(first_deeper[:, None], p2, p1)

    bodies = state.bodies
    separation = jnp.maximum(sep_a, sep_b)
    allowed = (
        bodies.active[tables.rr_a]
        & bodies.active[tables.rr_b]
        & modes_collide(bodies.collision_mode[tables.rr_a], bodies.collision_mode[tables.rr_b])
    )
    touching = allowed & (separation < 0)
    both_deep = touching & (depth1 > 0) & (depth2 > 0)
    penetration = -separation
    return (
        Contacts(touching, normal, point0, penetration),
        Contacts(both_deep, normal, point1, penetration),
    )


def _circle_polygon(state: SimState, tables: PairTables) -> Contacts:
    num_polygons = state.polygon_vertices.shape[0]
    bodies = state.bodies
    circle_body = tables.cr_circle + num_polygons
    poly = tables.cr_polygon
    radius = state.circle_radius[tables.cr_circle]
    poly_pos, poly_rot = bodies.position[poly], bodies.rotation[poly]
    # Work in the polygon's frame so its vertices need no transform.
    centre = rotate(-poly_rot, bodies.position[circle_body] - poly_pos)
    local = state.polygon_vertices[poly]  # [n, V, 2]
    n = state.polygon_n_vertices[poly][:, None]
    k = jnp.arange(local.shape[1])[None, :]
    valid = k < n
    local_next = jnp.take_along_axis(local, jnp.where(k + 1 < n, k + 1, 0)[..., None], axis=1)
    edge = local_next - local
    q = centre[:, None, :]
    t = jnp.clip(dot(q - local, edge) / nonzero(dot(edge, edge)), 0.0, 1.0)
    closest = local + t[..., None] * edge
    distance = jnp.sqrt(dot(q - closest, q - closest))
    distance = jnp.where(valid, distance, _FAR)
    inner_side = cross(local - q, local_next - q) < 0
    inside = jnp.all(inner_side | ~valid, axis=-1)
    nearest = jnp.argmin(distance, axis=-1)
    boundary = jnp.take_along_axis(closest, nearest[:, None, None], axis=1)[:, 0]
    gap = jnp.take_along_axis(distance, nearest[:, None], axis=1)[:, 0]
    away = jnp.where(inside[:, None], centre - boundary, boundary - centre)
    normal = rotate(poly_rot, away)
    normal = normal / nonzero(jnp.sqrt(dot(normal, normal)))[:, None]
    point = rotate(poly_rot, boundary) + poly_pos
    allowed = (
        bodies.active[circle_body]
        & bodies.active[poly]
        & modes_collide(bodies.collision_mode[circle_body], bodies.collision_mode[poly])
    )
    touching = allowed & ((gap <= radius) | inside)
    penetration = jnp.where(inside, radius, radius - gap)
    return Contacts(touching, normal, point, penetration)


def _circle_circle(state: SimState, tables: PairTables) -> Contacts:
    num_polygons = state.polygon_vertices.shape[0]
    bodies = state.bodies
    a, b = tables.cc_a + num_polygons, tables.cc_b + num_polygons
    ra, rb = state.circle_radius[tables.cc_a], state.circle_radius[tables.cc_b]
    offset = bodies.position[b] - bodies.position[a]
    distance = jnp.sqrt(dot(offset, offset))
    normal = offset / nonzero(distance)[:, None]
    allowed = (
        bodies.active[a] & bodies.active[b] & modes_collide(bodies.collision_mode[a], bodies.collision_mode[b])
    )
    touching = allowed & (distance < ra + rb)
    return Contacts(touching, normal, bodies.position[a] + ra[:, None] * normal, ra + rb - distance)


def detect_contacts(state: SimState, tables: PairTables) -> Contacts:
    """All contact slots of the scene, in slot order (rr point 0, rr point 1, circle-polygon, circle-circle)."""
    parts = []
    if tables.num_rr:
        parts += list(_polygon_polygon(state, tables))
    if tables.num_cr:
        parts.append(_circle_polygon(state, tables))
    if tables.num_cc:
        parts.append(_circle_circle(state, tables))
    if not parts:
        empty = jnp.zeros((0,))
        return Contacts(empty.astype(bool), jnp.zeros((0, 2)), jnp.zeros((0, 2)), empty)
    return Contacts(*(jnp.concatenate(field) for field in zip(*parts, strict=True)))
