"""Drawing a scene as an RGB image with Pillow (no GPU, no viewer: files, reports and tests).

It draws `engine.levels.drawing.SceneDrawing`, the geometry every renderer shares: a white background, the
5 m x 5 m arena with y up, shapes filled in their role colours with a darker outline, circles with a spoke showing
their rotation, joints as dots (welded joints as squares) and thrusters as small triangles pointing the way they
push, with a flame behind the ones firing. Unlike Kinetix's 125-pixel observation it draws outlines at any scale.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from impulse.engine.arena import ARENA_METRES, PIXELS_PER_METRE
from impulse.engine.levels.drawing import SceneDrawing, scene_drawing
from impulse.engine.levels.level import Level
from impulse.engine.physics.state import SimState

BACKGROUND = (255, 255, 255)
OUTLINE_DARKEN = 0.55
LINK_OUTLINE = (30, 30, 30)
FLAME = (255, 120, 0)


def _darker(colour: np.ndarray) -> tuple[int, int, int]:
    r, g, b = (int(c * OUTLINE_DARKEN) for c in colour)
    return r, g, b


def _rgb(colour: np.ndarray) -> tuple[int, int, int]:
    r, g, b = (int(c) for c in colour)
    return r, g, b


def image_size(scale: float = 1.0) -> int:
    """Side of the square image `render_scene` draws at `scale`, in pixels."""
    return max(1, round(ARENA_METRES * PIXELS_PER_METRE * scale))


def render_scene(drawing: SceneDrawing, scale: float = 1.0) -> np.ndarray:
    """The scene as an [H, W, 3] uint8 image, H = W = `image_size(scale)`, row 0 at the top (y = 5 m)."""
    if scale <= 0:
        raise ValueError(f"scale must be positive, got {scale}")
    ppm = PIXELS_PER_METRE * scale
    size = image_size(scale)
    line = max(1, round(2 * scale))
    thin = max(1, line // 2)

    def to_pixels(points: np.ndarray) -> list[tuple[float, float]]:
        return [(float(x * ppm), float(size - y * ppm)) for x, y in np.atleast_2d(points)]

    image = Image.new("RGB", (size, size), BACKGROUND)
    draw = ImageDraw.Draw(image)
    for outline, fill in zip(drawing.polygons, drawing.polygon_colours, strict=True):
        draw.polygon(to_pixels(outline), fill=_rgb(fill), outline=_darker(fill), width=line)
    for centre, radius, mark, fill in zip(drawing.circle_centres, drawing.circle_radii, drawing.circle_marks,
                                          drawing.circle_colours, strict=True):
        (cx, cy), r = to_pixels(centre)[0], radius * ppm
        draw.ellipse((cx - r, cy - r, cx + r, cy + r), fill=_rgb(fill), outline=_darker(fill), width=line)
        draw.line(to_pixels(np.stack([centre, mark])), fill=_darker(fill), width=line)

    dot = max(2.0, 0.05 * ppm)
    for anchor, welded, colour in zip(drawing.joint_positions, drawing.joint_welded, drawing.joint_colours,
                                      strict=True):
        x, y = to_pixels(anchor)[0]
        box = (x - dot, y - dot, x + dot, y + dot)
        shape = draw.rectangle if welded else draw.ellipse
        shape(box, fill=_rgb(colour), outline=LINK_OUTLINE, width=thin)

    for triangle, direction, colour, drive in zip(drawing.thruster_triangles, drawing.thruster_directions,
                                                  drawing.thruster_colours, drawing.thruster_drive, strict=True):
        if drive > 0:
            tail = (triangle[1] + triangle[2]) / 2
            flame = np.stack([triangle[1], triangle[2], tail - direction * drive * 0.2])
            draw.polygon(to_pixels(flame), fill=FLAME)
        draw.polygon(to_pixels(triangle), fill=_rgb(colour), outline=LINK_OUTLINE, width=thin)
    return np.asarray(image)


def render_level(level: Level, *, state: SimState | None = None, scale: float = 1.0) -> np.ndarray:
    """`render_scene` of one (unbatched) level, in `state` if given."""
    if scale <= 0:
        raise ValueError(f"scale must be positive, got {scale}")
    return render_scene(scene_drawing(level, state), scale)


def world_to_pixel(x: float, y: float, scale: float = 1.0) -> tuple[int, int]:
    """(row, column) of the pixel that shows world point (x, y) in an image from `render_scene`."""
    ppm = PIXELS_PER_METRE * scale
    size = image_size(scale)
    return int(np.clip(size - y * ppm, 0, size - 1)), int(np.clip(x * ppm, 0, size - 1))


def save_png(image: np.ndarray, path: str | Path) -> Path:
    """Write an [H, W, 3] uint8 image as PNG."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(image, np.uint8), "RGB").save(path, format="PNG")
    return path
