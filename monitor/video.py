"""Videos of episodes: every level's episode drawn by the PNG renderer (`monitor.png`) side by side in a grid, one
frame per agent step, written as an animated GIF or WebP (by Pillow) or an MP4 (H.264, yuv420p, by PyAV, whose
wheel bundles FFmpeg with libx264). A level whose episode has ended holds its last frame, framed in green if it was
solved and in red otherwise, until the longest episode ends.

`write_episodes_video` is the one way episodes become a video: `impulse eval --video FILE` (one episode per level
of a checkpoint's policy, as `--record` writes them to Rerun) and `impulse levels render --video FILE` (the levels
played with no-op actions) both call it with what `learner.evaluate.play_episodes` recorded.
"""

from __future__ import annotations

import math
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from impulse.engine.levels.drawing import scene_drawing
from impulse.monitor.png import render_scene

FORMATS = (".gif", ".webp", ".mp4")
DEFAULT_FPS = 30.0
"""Agent steps per second of video: Kinetix's agent acts at 30 Hz (frame_skip 2 of 60 Hz physics)."""
DEFAULT_SCALE = 0.4
"""Tile size as a multiple of Kinetix's 500 x 500 screen: 200 x 200 pixels per level."""
MP4_CRF = 18
"""libx264's constant rate factor: 18 is close to visually lossless for flat-coloured drawings."""
SOLVED_FRAME = (60, 170, 80)
UNSOLVED_FRAME = (200, 60, 60)
BORDER = 4


def _take(tree: Any, t: int, k: int) -> Any:
    import jax

    return jax.tree.map(lambda x: np.asarray(x)[t, k], tree)


def episode_grid_frames(states: Any, actuation: np.ndarray, keep: np.ndarray, solved: np.ndarray, names: list[str],
                        scale: float = DEFAULT_SCALE, columns: int | None = None) -> list[np.ndarray]:
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


def write_episodes_video(path: str | Path, names: list[str], episodes: Any, fps: float = DEFAULT_FPS,
                         scale: float = DEFAULT_SCALE) -> Path:
    """Draw recorded episodes side by side (`episode_grid_frames`) and write them to `path` (`save_video`).
    `episodes` is a `learner.evaluate.RecordedEpisodes` (taken by its fields: this room sits below the learner's):
    `watched.state`, `watched.actuation`, `first` and `steps.solved`, all [T, K]; `names` label the K tiles (a
    level file's path is shown by its stem)."""
    check_video_path(path)
    labels = [Path(name).stem or name for name in names]
    frames = episode_grid_frames(episodes.watched.state, episodes.watched.actuation, episodes.first,
                                 episodes.steps.solved, labels, scale)
    return save_video(frames, path, fps)


def check_video_path(path: str | Path) -> None:
    """Raise ValueError unless `path` names a video format `save_video` writes (checked before playing anything)."""
    if Path(path).suffix.lower() not in FORMATS:
        raise ValueError(f"video {path}: write {', '.join(FORMATS[:-1])} or {FORMATS[-1]}, not "
                         f"{Path(path).suffix or 'a file without a suffix'!r}")


def save_video(frames: list[np.ndarray], path: str | Path, fps: float = DEFAULT_FPS) -> Path:
    """Write `frames` [H, W, 3] uint8 as an animated GIF or WebP (looping) or an MP4, by the file's suffix, at `fps`
    frames per second."""
    path = Path(path)
    check_video_path(path)
    if not frames:
        raise ValueError("no frames to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".mp4":
        return _save_mp4(frames, path, fps)
    images = [Image.fromarray(np.asarray(frame, np.uint8)) for frame in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return path


def even_size(frame: np.ndarray) -> tuple[int, int]:
    """(height, width) of `frame` rounded up to even numbers, as yuv420p needs (its colour is sampled per 2 x 2)."""
    height, width = frame.shape[:2]
    return height + height % 2, width + width % 2


def _save_mp4(frames: list[np.ndarray], path: Path, fps: float) -> Path:
    """H.264 in yuv420p (what browsers and players open), one video frame per frame, padded with white on the
    right and bottom to even sizes; the index up front (faststart) so a browser can play it while it loads."""
    import av

    height, width = even_size(frames[0])
    with av.open(str(path), "w", format="mp4", options={"movflags": "+faststart"}) as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"crf": str(MP4_CRF), "preset": "medium"}
        canvas = np.full((height, width, 3), 255, np.uint8)
        for frame in frames:
            frame = np.asarray(frame, np.uint8)
            canvas[: frame.shape[0], : frame.shape[1]] = frame[:, :, :3]
            container.mux(stream.encode(av.VideoFrame.from_ndarray(canvas, format="rgb24")))
        container.mux(stream.encode())  # flush the encoder's delayed frames
    return path
