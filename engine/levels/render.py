"""Drawing a level's scene as an RGB image (numpy and Pillow only: no GPU, usable from any process).

The picture follows Kinetix's pixel renderer where it matters for reading a level: a white background, the
5 m x 5 m arena with y up, shapes filled in their role colours (fixed shapes darker: neutral becomes dark grey,
the other roles half as bright), circles with a line from the centre showing their rotation, joints as dots
(fixed joints as squares) and thrusters as small triangles pointing the way they push, both coloured by the
action binding that drives them. Unlike Kinetix's 125-pixel observation it draws outlines at every scale.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from engine.levels.level import Level
from engine.physics.state import SimState

ARENA_METRES = 5.0
PIXELS_PER_METRE = 100.0  # Kinetix's pixels_per_unit: the arena is 500 x 500 pixels at scale 1

BACKGROUND = (255, 255, 255)
ROLE_COLOURS = (
    (160, 160, 160),  # neutral
    (0, 204, 0),  # green
    (0, 102, 204),  # blue
    (255, 102, 102),  # red
)
FIXED_NEUTRAL = (80, 80, 80)
# Joints and thrusters by binding + 1; index 0 (white) for joints without a motor and for fixed joints.
BINDING_COLOURS = ((255, 255, 255), (255, 255, 0), (255, 0, 255), (0, 255, 255), (255, 153, 51))
OUTLINE_DARKEN = 0.55
LINK_OUTLINE = (30, 30, 30)


def shape_colour(role: int, fixed: bool) -> tuple[int, int, int]:
    """Fill colour of a shape: its role colour, darker when the shape is fixed (inverse mass 0)."""
    role = int(role) if 0 <= int(role) < len(ROLE_COLOURS) else 0
    if not fixed:
        return ROLE_COLOURS[role]
    if role == 0:
        return FIXED_NEUTRAL
    return tuple(int(c * 0.5) for c in ROLE_COLOURS[role])  # type: ignore[return-value]


def _darker(colour: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple(int(c * OUTLINE_DARKEN) for c in colour)  # type: ignore[return-value]


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def render_level(level: Level, *, state: SimState | None = None, scale: float = 1.0) -> np.ndarray:
    """The scene as an [H, W, 3] uint8 image, H = W = round(500 * scale), row 0 at the top (y = 5 m).

    `state` replaces the level's initial scene (e.g. a state from a rollout); roles and bindings still come from
    `level`. Takes one unbatched level.
    """
    if scale <= 0:
        raise ValueError(f"scale must be positive, got {scale}")
    s = state if state is not None else level.state
    if np.ndim(s.bodies.rotation) != 1:
        raise ValueError(f"render_level draws one scene, got a batch of shape {np.shape(s.bodies.rotation)[:-1]}")
    roles = np.asarray(level.roles)
    motor_bindings = np.asarray(level.motor_bindings)
    thruster_bindings = np.asarray(level.thruster_bindings)
    position = np.asarray(s.bodies.position, np.float64)
    rotation = np.asarray(s.bodies.rotation, np.float64)
    active = np.asarray(s.bodies.active)
    fixed = np.asarray(s.bodies.inverse_mass) == 0
    vertices = np.asarray(s.polygon_vertices, np.float64)
    n_vertices = np.asarray(s.polygon_n_vertices)
    radius = np.asarray(s.circle_radius, np.float64)
    P = vertices.shape[0]

    ppm = PIXELS_PER_METRE * scale
    size = max(1, round(ARENA_METRES * ppm))
    line = max(1, round(2 * scale))

    def to_pixels(points: np.ndarray) -> list[tuple[float, float]]:
        points = np.atleast_2d(points)
        return [(float(x * ppm), float(size - y * ppm)) for x, y in points]

    image = Image.new("RGB", (size, size), BACKGROUND)
    draw = ImageDraw.Draw(image)

    for p in range(P):
        if not active[p]:
            continue
        n = int(np.clip(n_vertices[p], 0, vertices.shape[1]))
        if n < 3:
            continue
        world = position[p] + vertices[p, :n] @ _rotation(rotation[p]).T
        fill = shape_colour(roles[p], fixed[p])
        draw.polygon(to_pixels(world), fill=fill, outline=_darker(fill), width=line)

    for c in range(radius.shape[0]):
        body = P + c
        if not active[body]:
            continue
        fill = shape_colour(roles[body], fixed[body])
        (cx, cy), r = to_pixels(position[body])[0], radius[c] * ppm
        draw.ellipse((cx - r, cy - r, cx + r, cy + r), fill=fill, outline=_darker(fill), width=line)
        tip = position[body] + radius[c] * np.array([np.cos(rotation[body]), np.sin(rotation[body])])
        draw.line(to_pixels(np.stack([position[body], tip])), fill=_darker(fill), width=line)

    joints = s.joints
    dot = max(2.0, 0.05 * ppm)
    for j in np.flatnonzero(np.asarray(joints.active)):
        a = int(np.asarray(joints.a_index)[j])
        if not 0 <= a < position.shape[0]:
            continue
        anchor = position[a] + _rotation(rotation[a]) @ np.asarray(joints.a_relative_pos[j], np.float64)
        x, y = to_pixels(anchor)[0]
        welded = bool(np.asarray(joints.is_fixed_joint)[j])
        motor = bool(np.asarray(joints.motor_on)[j]) and not welded
        binding = int(motor_bindings[j])
        colour = BINDING_COLOURS[binding + 1] if motor and 0 <= binding < 4 else BINDING_COLOURS[0]
        box = (x - dot, y - dot, x + dot, y + dot)
        if welded:
            draw.rectangle(box, fill=colour, outline=LINK_OUTLINE, width=max(1, line // 2))
        else:
            draw.ellipse(box, fill=colour, outline=LINK_OUTLINE, width=max(1, line // 2))

    thrusters = s.thrusters
    length = max(6.0, 0.16 * ppm)
    for t in np.flatnonzero(np.asarray(thrusters.active)):
        body = int(np.asarray(thrusters.body_index)[t])
        if not 0 <= body < position.shape[0]:
            continue
        turn = _rotation(rotation[body])
        base = position[body] + turn @ np.asarray(thrusters.relative_position[t], np.float64)
        angle = rotation[body] + float(np.asarray(thrusters.rotation)[t])
        ahead = np.array([np.cos(angle), np.sin(angle)])
        side = np.array([-ahead[1], ahead[0]])
        metres = length / ppm
        triangle = np.stack([base + ahead * metres * 0.6, base - ahead * metres * 0.4 + side * metres * 0.35,
                             base - ahead * metres * 0.4 - side * metres * 0.35])
        binding = int(thruster_bindings[t])
        colour = BINDING_COLOURS[binding + 1] if 0 <= binding < 2 else BINDING_COLOURS[0]
        draw.polygon(to_pixels(triangle), fill=colour, outline=LINK_OUTLINE, width=max(1, line // 2))

    return np.asarray(image)


def world_to_pixel(x: float, y: float, scale: float = 1.0) -> tuple[int, int]:
    """(row, column) of the pixel that shows world point (x, y) in an image from `render_level`."""
    ppm = PIXELS_PER_METRE * scale
    size = max(1, round(ARENA_METRES * ppm))
    return int(np.clip(size - y * ppm, 0, size - 1)), int(np.clip(x * ppm, 0, size - 1))


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an [H, W, 3] uint8 image as PNG."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(image, np.uint8), "RGB").save(path, format="PNG")
    return path
