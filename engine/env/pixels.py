"""Kinetix's pixel observation: the scene drawn into a small RGB image, in JAX, inside the jitted env step.

Layout (Kinetix digest, section 7.5): float32 in [0, 1] of shape (500 / downscale, 500 / downscale, 3), indexed
[x, y] with y up, so pixel (i, j) shows the world point (i, j) / (100 // downscale) metres; `global_info` is
[gravity_y / 10]. Drawing order: white background, the floor as one quad in its (fixed) role colour, the
non-arena polygons, the circles (each with a dark spoke showing its rotation), joints (one pixel at downscale 4,
a small glyph otherwise), thrusters (a nozzle-and-flame glyph rotated with the push direction). Shape colours and
the binding palette are the monitor's (`engine.levels.drawing`), with Kinetix's float halving of fixed coloured
shapes. Edges: 2 px outlines at downscale 1, 1 px at 2, none at 4.

To agree with Kinetix pixel for pixel, the sampling rules copy its behaviour rather than an ideal renderer: a
pixel samples the integer point of its index (no half-pixel centre), edge tests keep the boundary (<= 0), and every
shape is drawn only inside a square window of 2 m around its centre of mass (Kinetix renders each shape into a
fixed-size patch, so parts of shapes reaching further than 1 m from their centre are cut off; the floor is
exempt). Deliberate differences: triangles are drawn as triangles (Kinetix always draws four vertices, the
padding vertex included), and the joint and thruster glyphs are our own drawings (Kinetix uses bitmap textures
shipped with it), so those few pixels differ. A pixel exactly on a shape's boundary can also flip where XLA fuses
the pixel-space transform into the edge test and contracts it into a fused multiply-add (Kinetix rounds first);
`benchmarks/pixels.py` measures both effects.

Everything is one vectorised pass (no per-shape loops at trace time beyond a static handful): each drawn thing is
a boolean layer over the whole image, and a pixel takes the colour of the last layer covering it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.arena import PIXELS_PER_METRE, SCREEN_PIXELS
from impulse.engine.env.observation_types import PixelObservation
from impulse.engine.levels.drawing import FIXED_NEUTRAL, MOTOR_BINDING_COLOURS, ROLE_COLOURS, UNBOUND
from impulse.engine.levels.level import Level
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState

Array = jax.Array

WINDOW_METRES = 2
"""Side of the square around each shape's centre outside which it is not drawn (Kinetix's max_shape_size)."""
JOINT_GLYPH_PIXELS = 6
"""Joint glyph side at downscale 1 (at downscale 4 a joint is a single pixel)."""
THRUSTER_GLYPH_PIXELS = 16
"""Thruster glyph side at downscale 1 (the glyph is a 16 x 16 grid sampled nearest-neighbour)."""
BACKGROUND = (255.0, 255.0, 255.0)
JOINT_PALETTE = np.asarray((UNBOUND, *MOTOR_BINDING_COLOURS), np.float32)
"""Joint and thruster colours by (binding + 1), index 0 for joints without a driven motor."""


def _thruster_glyph() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Our thruster drawing on a 16 x 16 grid, first axis along the push direction (index 15 leads): a nozzle of
    dark grey with a black outline at the front, a cone of exhaust behind it whose greys are tinted by the binding
    colour. Returns (class per cell [16, 16] int, 0 empty; grey level per class; tinted per class)."""
    n = THRUSTER_GLYPH_PIXELS
    u, v = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    across = np.abs(v - (n - 1) / 2)
    nozzle_start = 9
    nozzle_half = n / 2 - 0.5 * np.maximum(u - nozzle_start, 0)
    in_nozzle = (u >= nozzle_start) & (across <= nozzle_half)
    nozzle_rim = in_nozzle & ((u == nozzle_start) | (u == n - 1) | (across > nozzle_half - 1))
    flame_half = 0.75 + 0.6 * u
    in_flame = (u < nozzle_start) & (across <= flame_half)
    flame_rim = in_flame & (across > flame_half - 1)
    flame_core = in_flame & (u >= 6) & (across <= 1)
    cls = np.zeros((n, n), np.int32)
    cls[in_flame] = 1
    cls[flame_rim] = 2
    cls[flame_core] = 3
    cls[in_nozzle] = 4
    cls[nozzle_rim] = 5
    grey = np.asarray([0.0, 196.0, 132.0, 255.0, 93.0, 0.0], np.float32)
    tinted = np.asarray([False, True, True, True, False, False])
    return cls, grey, tinted


THRUSTER_GLYPH, THRUSTER_GREYS, THRUSTER_TINTED = _thruster_glyph()


@dataclass(frozen=True)
class PixelGeometry:
    """Static pixel sizes for one downscale factor (integer arithmetic as in Kinetix)."""

    downscale: int
    pixels_per_metre: int
    size: int
    """Side of the observed image."""
    margin: int
    """Kinetix draws into an image padded by this many pixels on every side, then crops: coordinates below are in
    that padded frame, so that float rounding matches its own."""
    window: int
    edge_thickness: int
    joint_pixels: int
    joint_glyphs: bool
    """Joints as glyphs (outlined disc or square); at downscale 4 a joint is one pixel."""
    thruster_pixels: int
    thruster_window: int

    @property
    def padded(self) -> int:
        return self.size + 2 * self.margin


@functools.cache
def pixel_geometry(downscale: int) -> PixelGeometry:
    """The pixel sizes Kinetix uses at `downscale` (1, 2 and 4 are its named cases; other factors follow the
    downscale-1 edge and glyph rules, as in Kinetix)."""
    if downscale < 1 or SCREEN_PIXELS % downscale:
        raise ValueError(f"pixel downscale must be a positive divisor of {SCREEN_PIXELS}, got {downscale}")
    ppm = PIXELS_PER_METRE // downscale
    edge = {2: 1, 4: 0}.get(downscale, 2)
    thruster = math.ceil((THRUSTER_GLYPH_PIXELS // downscale) * PIXELS_PER_METRE / 100)
    return PixelGeometry(
        downscale=downscale,
        pixels_per_metre=ppm,
        size=SCREEN_PIXELS // downscale,
        margin=WINDOW_METRES * ppm,
        window=WINDOW_METRES * ppm,
        edge_thickness=edge,
        joint_pixels=math.ceil((JOINT_GLYPH_PIXELS // downscale) * PIXELS_PER_METRE / 100),
        joint_glyphs=downscale != 4,
        thruster_pixels=thruster,
        thruster_window=int(thruster * np.sqrt(2)) + 1,
    )


def world_polygon_vertices(position: Array, rotation: Array, local: Array) -> Array:
    """World vertices [..., V, 2] of polygons at `position` [..., 2] turned by `rotation` [...] from local
    vertices [..., V, 2] (rotation applied to each vertex, then the translation)."""
    c, s = jnp.cos(rotation), jnp.sin(rotation)
    turn = jnp.stack([jnp.stack([c, -s], axis=-1), jnp.stack([s, c], axis=-1)], axis=-2)  # [..., 2, 2]
    turned = jnp.matmul(turn[..., None, :, :], local[..., None])[..., 0]  # a matrix product, like Kinetix
    return position[..., None, :] + turned


def _to_padded(geometry: PixelGeometry, world: Array) -> Array:
    return (world + WINDOW_METRES) * geometry.pixels_per_metre


def _window_mask(geometry: PixelGeometry, start: Array, side: int, coords: Array) -> Array:
    """[..., W, H] true inside the square of `side` pixels starting at `start` [..., 2] (padded frame), which is
    clamped into the padded image as a fixed-size slice would be."""
    start = jnp.clip(jnp.maximum(start, 0), 0, geometry.padded - side)
    in_x = (coords[None, :] >= start[..., 0:1]) & (coords[None, :] < start[..., 0:1] + side)
    in_y = (coords[None, :] >= start[..., 1:2]) & (coords[None, :] < start[..., 1:2] + side)
    return in_x[..., :, None] & in_y[..., None, :]


def _shape_window(geometry: PixelGeometry, position: Array, coords: Array) -> Array:
    start = _to_padded(geometry, position - WINDOW_METRES / 2.0).astype(jnp.int32)
    return _window_mask(geometry, start, geometry.window, coords)


def _polygon_layers(geometry: PixelGeometry, vertices: Array, n_vertices: Array, coords: Array) -> tuple[Array, Array]:
    """(inside, on the edge band) [K, W, H] for convex clockwise polygons given in padded pixel coordinates
    [K, V, 2] with n_vertices [K] used vertices."""
    V = vertices.shape[1]
    px, py = coords[None, :, None], coords[None, None, :]
    inside = jnp.ones((vertices.shape[0], coords.size, coords.size), bool)
    edge = jnp.zeros_like(inside)
    for k in range(V):
        following = jnp.where(k + 1 < n_vertices, k + 1, 0)
        a = vertices[:, k]
        b = jnp.take_along_axis(vertices, following[:, None, None], axis=1)[:, 0]
        ax, ay, bx, by = (t[:, None, None] for t in (a[:, 0], a[:, 1], b[:, 0], b[:, 1]))
        side = (ax - px) * (by - py) - (ay - py) * (bx - px)
        used = (k < n_vertices)[:, None, None]
        inside &= (side <= 0) | ~used
        if geometry.edge_thickness:
            distance = side / jnp.linalg.norm(a - b, axis=-1)[:, None, None]
            edge |= used & (distance > -geometry.edge_thickness) & (side <= 0)
    return inside, edge & inside


def _shape_colours(roles: Array, fixed: Array) -> Array:
    """[K, 3] fill colours 0..255: the role colour; fixed shapes dark grey (neutral) or at half brightness."""
    base = jnp.asarray(ROLE_COLOURS, jnp.float32)[roles]
    fixed_colour = jnp.where((roles == 0)[:, None], jnp.asarray(FIXED_NEUTRAL, jnp.float32), base * 0.5)
    return jnp.where(fixed[:, None], fixed_colour, base)


def _joint_layers(geometry: PixelGeometry, sim: SimState, level: Level, coords: Array) -> tuple[Array, Array]:
    j = sim.joints
    driven = j.motor_on & ~j.is_fixed_joint
    colour = jnp.asarray(JOINT_PALETTE)[jnp.where(driven, level.motor_bindings + 1, 0)]
    half = geometry.joint_pixels // 2
    start = jnp.round(_to_padded(geometry, j.global_position) - half).astype(jnp.int32)
    window = _window_mask(geometry, start, geometry.joint_pixels, coords) & j.active[:, None, None]
    clamped = jnp.clip(jnp.maximum(start, 0), 0, geometry.padded - geometry.joint_pixels)
    if not geometry.joint_glyphs:
        # A disc of diameter 1 centred on a pixel: exactly that pixel, unless the window was pushed aside.
        on_target = jnp.all(clamped == start, axis=-1)[:, None, None]
        return (window & on_target)[:, None], colour[:, None]
    # Our glyph: revolute joints an outlined disc, welded joints an outlined square, inside in the joint colour.
    size = geometry.joint_pixels
    du = coords[None, :] - clamped[:, 0:1] - (size - 1) / 2
    dv = coords[None, :] - clamped[:, 1:2] - (size - 1) / 2
    du, dv = du[:, :, None], dv[:, None, :]
    radius = size / 2
    disc = du**2 + dv**2 <= radius**2
    ring = disc & (du**2 + dv**2 > (radius - 1) ** 2)
    square_rim = (jnp.abs(du) > radius - 1) | (jnp.abs(dv) > radius - 1)
    welded = j.is_fixed_joint[:, None, None]
    body = window & jnp.where(welded, True, disc)
    rim = body & jnp.where(welded, square_rim, ring)
    layers = jnp.stack([body, rim], axis=1)
    colours = jnp.stack([colour, jnp.zeros_like(colour)], axis=1)
    return layers, colours


def _thruster_layers(geometry: PixelGeometry, sim: SimState, level: Level, coords: Array) -> tuple[Array, Array]:
    t = sim.thrusters
    rotation = t.rotation + sim.bodies.rotation[t.body_index]
    centre = jnp.round(_to_padded(geometry, t.global_position)).astype(jnp.int32)
    window = _window_mask(geometry, centre - geometry.thruster_window // 2, geometry.thruster_window, coords)
    dx = (coords[None, :, None] - centre[:, 0, None, None]).astype(jnp.float32)
    dy = (coords[None, None, :] - centre[:, 1, None, None]).astype(jnp.float32)
    c, s = jnp.cos(-rotation)[:, None, None], jnp.sin(-rotation)[:, None, None]
    size = geometry.thruster_pixels
    u = (c * dx - s * dy) / size + 0.5
    v = (s * dx + c * dy) / size + 0.5
    on_glyph = (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1) & window & t.active[:, None, None]
    n = THRUSTER_GLYPH_PIXELS
    cell_u = jnp.clip(jnp.round(n * u - 0.5 + 1e-3), 0, n - 1).astype(jnp.int32)
    cell_v = jnp.clip(jnp.round(n * v - 0.5 + 1e-3), 0, n - 1).astype(jnp.int32)
    cls = jnp.asarray(THRUSTER_GLYPH)[cell_u, cell_v]
    num_classes = THRUSTER_GREYS.size - 1
    layers = jnp.stack([on_glyph & (cls == k) for k in range(1, num_classes + 1)], axis=1)
    tint = jnp.asarray(JOINT_PALETTE)[level.thruster_bindings + 1] / 255.0
    greys = jnp.asarray(THRUSTER_GREYS[1:])[None, :, None]
    tinted = jnp.asarray(THRUSTER_TINTED[1:])[None, :, None]
    colours = greys * jnp.where(tinted, tint[:, None, :], 1.0)
    return layers, colours


def _add_outlined(
    layers: list[Array], colours: list[Array], inside: Array, edge: Array, fill: Array, geometry: PixelGeometry
) -> None:
    """Append shapes [K, W, H] in `fill` [K, 3], each followed by its outline band in black (none at downscale 4,
    so no layer is spent on it)."""
    if not geometry.edge_thickness:
        layers.append(inside)
        colours.append(fill)
        return
    layers.append(jnp.stack([inside, edge], axis=1))
    colours.append(jnp.stack([fill, jnp.zeros_like(fill)], axis=1))


def render_pixels(sim: SimState, level: Level, sizes: SceneSizes, downscale: int = 4) -> Array:
    """The scene as Kinetix's pixel observation draws it: [size, size, 3] float32 in [0, 1], indexed [x, y]."""
    masks, palette = pixel_layers(sim, level, sizes, downscale)
    order = jnp.arange(1, masks.shape[0] + 1, dtype=jnp.int32)[:, None, None]
    top = jnp.max(jnp.where(masks, order, 0), axis=0)
    return palette[top] / 255.0


def pixel_layers(sim: SimState, level: Level, sizes: SceneSizes, downscale: int = 4) -> tuple[Array, Array]:
    """Everything drawn, in drawing order: masks [L, size, size] bool and the palette [1 + L, 3] (0..255) whose
    row 0 is the background and row k + 1 the colour of layer k. A pixel shows its last covering layer."""
    geometry = pixel_geometry(downscale)
    S, P = sizes.num_static_polygons, sizes.num_polygons
    b = sim.bodies
    coords = jnp.arange(geometry.size, dtype=jnp.int32) + geometry.margin
    fcoords = coords.astype(jnp.float32)
    fixed = b.inverse_mass == 0
    layers: list[Array] = []  # each [K, W, H] or [K, k, W, H], drawn in order
    colours: list[Array] = []

    if S > 0:
        floor = _to_padded(geometry, b.position[0, None, :] + sim.polygon_vertices[0])[None]
        inside, edge = _polygon_layers(geometry, floor, sim.polygon_n_vertices[:1], fcoords)
        floor_colour = _shape_colours(level.roles[:1], jnp.ones((1,), bool))
        _add_outlined(layers, colours, inside, edge, floor_colour, geometry)

    if P > S:
        world = world_polygon_vertices(b.position[S:P], b.rotation[S:P], sim.polygon_vertices[S:])
        vertices = _to_padded(geometry, world)
        inside, edge = _polygon_layers(geometry, vertices, sim.polygon_n_vertices[S:], fcoords)
        drawn = _shape_window(geometry, b.position[S:P], coords) & b.active[S:P, None, None]
        fill = _shape_colours(level.roles[S:P], fixed[S:P])
        _add_outlined(layers, colours, inside & drawn, edge & drawn, fill, geometry)

    if sizes.num_circles:
        centre = _to_padded(geometry, b.position[P:])
        radius = (sim.circle_radius * geometry.pixels_per_metre)[:, None, None]
        px, py = fcoords[None, :, None], fcoords[None, None, :]
        cx, cy = centre[:, 0, None, None], centre[:, 1, None, None]
        distance = jnp.sqrt(jnp.square(px - cx) + jnp.square(py - cy))
        inside = (distance <= radius) & _shape_window(geometry, b.position[P:], coords) & b.active[P:, None, None]
        # The spoke: within 1 px of the line through the centre along (-sin, cos) of the rotation, on that side.
        nx, ny = jnp.sin(b.rotation[P:])[:, None, None], -jnp.cos(b.rotation[P:])[:, None, None]
        off_line = jnp.abs((cx - px) * ((cy + ny) - py) - (cy - py) * ((cx + nx) - px))
        spoke = (off_line < 1) & (nx * (px - cx) + ny * (py - cy) <= 0)
        if geometry.edge_thickness:
            spoke |= distance > radius - geometry.edge_thickness
        fill = _shape_colours(level.roles[P:], fixed[P:])
        layers += [jnp.stack([inside, inside & spoke], axis=1)]
        colours += [jnp.stack([fill, jnp.zeros_like(fill)], axis=1)]

    if sizes.num_joints:
        joint_layers, joint_colours = _joint_layers(geometry, sim, level, coords)
        layers.append(joint_layers)
        colours.append(joint_colours)
    if sizes.num_thrusters:
        thruster_layers, thruster_colours = _thruster_layers(geometry, sim, level, coords)
        layers.append(thruster_layers)
        colours.append(thruster_colours)

    masks = jnp.concatenate([m.reshape((-1,) + m.shape[-2:]) for m in layers])
    palette = jnp.concatenate([jnp.asarray([BACKGROUND], jnp.float32)] + [c.reshape(-1, 3) for c in colours])
    return masks, palette


def pixel_observation(sim: SimState, level: Level, sizes: SceneSizes, downscale: int = 4) -> PixelObservation:
    """Kinetix's PIXELS observation of one environment: the image and [gravity_y / 10]."""
    return PixelObservation(
        image=render_pixels(sim, level, sizes, downscale),
        global_info=(sim.gravity[1:2] / 10.0).astype(jnp.float32),
    )
