"""Mass properties of shapes from their geometry and density.

Two conventions:
- "physical" (our default for scenes we build): area centroid, exact polygon inertia about it, circle inertia
  m r^2 / 2.
- "jax2d": what Jax2D's helpers compute and what Kinetix level files therefore store: the centre of mass is the
  vertex average, a triangle's inertia closes its fan through the padding vertex slot, and a circle's inertia is
  m r^2 / 4. Use it when editing or mutating Kinetix levels so new values match the ones already stored.
Loaded levels keep the inverse masses and inertias they carry; nothing here runs on them unless asked.
"""

from __future__ import annotations

from typing import Literal

import jax.numpy as jnp

from impulse.engine.physics.geometry import cross, dot, nonzero

Array = jnp.ndarray
MassConvention = Literal["physical", "jax2d"]


def _inverse(x: Array) -> Array:
    return jnp.where(x == 0, 0.0, 1.0 / nonzero(x))


def polygon_mass_properties(
    vertices: Array, n_vertices: int, density: Array, convention: MassConvention = "physical"
) -> tuple[Array, Array, Array, Array]:
    """For local vertices [V, 2] (first n used, clockwise): (centre of mass offset, recentred vertices [V, 2],
    inverse mass, inverse inertia about the centre of mass)."""
    max_vertices = vertices.shape[0]
    k = jnp.arange(max_vertices)
    valid = k < n_vertices
    nxt = vertices[jnp.where(k + 1 < n_vertices, k + 1, 0)]
    edge_cross = jnp.where(valid, cross(vertices, nxt), 0.0)
    signed_area = 0.5 * edge_cross.sum()
    area = jnp.abs(signed_area)
    if convention == "physical":
        centre = ((vertices + nxt) * edge_cross[:, None]).sum(axis=0) / (6.0 * nonzero(signed_area))
        local = vertices - centre
        local_next = nxt - centre
        terms = jnp.abs(cross(local, local_next)) * (
            dot(local, local) + dot(local, local_next) + dot(local_next, local_next)
        )
        inertia = density * jnp.where(valid, terms, 0.0).sum() / 12.0
    else:
        centre = jnp.where(valid[:, None], vertices, 0.0).sum(axis=0) / n_vertices
        local = vertices - centre  # every slot is shifted, padding included, as Jax2D does
        wrapped = local[(k + 1) % max_vertices]
        terms = jnp.abs(cross(wrapped, local)) * (dot(local, local) + dot(local, wrapped) + dot(wrapped, wrapped))
        inertia = density * jnp.where(valid, terms, 0.0).sum() / 12.0
    mass = density * area
    return centre, jnp.where(valid[:, None], local, 0.0), _inverse(mass), _inverse(inertia)


def circle_mass_properties(
    radius: Array, density: Array, convention: MassConvention = "physical"
) -> tuple[Array, Array]:
    """(inverse mass, inverse inertia) of a solid disc."""
    mass = density * jnp.pi * radius**2
    inertia = mass * radius**2 / (2.0 if convention == "physical" else 4.0)
    return _inverse(mass), _inverse(inertia)
