"""Videos of episodes: every level's episode drawn by the PNG renderer (`monitor.png`) side by side in a grid, one
frame per agent step, written as an animated GIF or WebP by Pillow. A level whose episode has ended holds its last
frame, framed in green if it was solved and in red otherwise, until the longest episode ends.

Used by `impulse eval --video FILE.gif` (one episode per level, as `--record` writes them to Rerun).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from impulse.engine.levels.drawing import scene_drawing
from impulse.monitor.png import render_scene
from PIL import Image, ImageDraw

FORMATS = (".gif", ".webp")
SOLVED_FRAME = (60, 170, 80)
UNSOLVED_FRAME = (200, 60, 60)
BORDER = 4


def _take(tree: Any, t: int, k: int) -> Any:
    import jax

    return jax.tree.map(lambda x: np.asarray(x)[t, k], tree)


def episode_grid_frames(states: Any, actuation: np.ndarray, keep: np.ndarray, solved: np.ndarray, names: list[str],
                        scale: float = 0.4, columns: int | None = None) -> list[np.ndarray]:
    """Frames [H, W, 3] uint8 of K episodes side by side, one per step of the longest episode and a last one with
    every outcome framed. `states` is an EnvState with [T, K] leading axes (the scene before each step),
    `actuation` [T, K, J + T_thrusters] what each step drove, `keep` [T, K] whether the step belongs to the
    episode shown, `solved` [T, K] whether that step solved it."""
    keep = np.asarray(keep, bool)
    steps, count = keep.shape
    lengths = keep.sum(axis=0)
    won = (np.asarray(solved, bool) & keep).any(axis=0)
    columns = columns or min(count, max(1, math.ceil(math.sqrt(count))))
    rows = math.ceil(count / columns)
    frames, tiles = [], [None] * count
    for t in range(int(lengths.max(initial=0)) + 1):  # one frame more: the last shows every outcome
        for k in range(count):
            if t < lengths[k]:
                state = _take(states, t, k)
                tiles[k] = render_scene(scene_drawing(state.level, state.sim, np.asarray(actuation)[t, k]), scale)
            elif t == lengths[k]:  # ended: hold the last frame, framed by the outcome
                tiles[k] = _framed(tiles[k], SOLVED_FRAME if won[k] else UNSOLVED_FRAME)
        frames.append(_grid(tiles, names, rows, columns))
    return frames


def _framed(tile: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    framed = tile.copy()
    framed[:BORDER], framed[-BORDER:], framed[:, :BORDER], framed[:, -BORDER:] = colour, colour, colour, colour
    return framed


def _grid(tiles: list[np.ndarray | None], names: list[str], rows: int, columns: int) -> np.ndarray:
    size = next(t for t in tiles if t is not None).shape[0]
    canvas = Image.new("RGB", (columns * size, rows * size), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for k, tile in enumerate(tiles):
        if tile is None:
            continue
        x, y = (k % columns) * size, (k // columns) * size
        canvas.paste(Image.fromarray(tile), (x, y))
        draw.text((x + BORDER + 2, y + BORDER + 2), names[k], fill=(30, 30, 30))
    return np.asarray(canvas)


def save_video(frames: list[np.ndarray], path: str | Path, fps: float = 30.0) -> Path:
    """Write `frames` as an animated GIF or WebP (by the file's suffix), looping, at `fps` frames per second."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"video {path}: write {' or '.join(FORMATS)} (animated, by Pillow), not {path.suffix!r}")
    if not frames:
        raise ValueError("no frames to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(np.asarray(frame, np.uint8)) for frame in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return path
