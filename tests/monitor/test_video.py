"""Videos of evaluation episodes (monitor/video.py): one tile per level, a frame per step of the longest episode
plus a last one on which each tile is framed by its outcome, written as an animated GIF that reads back with as
many frames, and as an MP4 (H.264, yuv420p, padded to even sizes) that PyAV reads back frame for frame, close to
the drawn pixels. The scenes are hand-made levels in their start state, held for a few steps."""

from __future__ import annotations

from pathlib import Path

import av
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from impulse.engine.env.state import initial_state
from impulse.engine.levels.sets import load_level_set
from impulse.engine.physics.sizes import SIZE_S
from impulse.monitor.video import BORDER, SOLVED_FRAME, UNSOLVED_FRAME, episode_grid_frames, save_video

STEPS = 4


@pytest.fixture(scope="module")
def episodes():
    names, levels = load_level_set("handmade:s_easy_car_right,s_lander,s_hop_over", SIZE_S)
    states = jax.vmap(initial_state)(levels)
    held = jax.tree.map(lambda x: jnp.broadcast_to(x, (STEPS, *x.shape)), states)  # [T, K]
    keep = np.array([[True, True, True], [True, False, True], [True, False, True], [False, False, True]])
    solved = np.zeros((STEPS, 3), bool)
    solved[2, 0] = True  # the first level's episode ends solved at step 2; the second ends unsolved at step 0
    actuation = np.zeros((STEPS, 3, levels.motor_bindings.shape[1] + levels.thruster_bindings.shape[1]), np.float32)
    return names, held, actuation, keep, solved


def test_tiles_are_framed_by_outcome_when_their_episode_ends(episodes, tmp_path: Path) -> None:
    names, states, actuation, keep, solved = episodes
    frames = episode_grid_frames(states, actuation, keep, solved, names, scale=0.2, columns=3)
    assert len(frames) == STEPS + 1
    tile = frames[0].shape[1] // 3
    corner = lambda frame, k: tuple(frame[BORDER // 2, k * tile + tile // 2])  # noqa: E731  top edge, mid tile
    assert corner(frames[0], 1) != UNSOLVED_FRAME  # still playing at step 0
    assert corner(frames[1], 1) == UNSOLVED_FRAME  # ended after 1 step, unsolved
    assert corner(frames[3], 0) == SOLVED_FRAME and corner(frames[2], 0) != SOLVED_FRAME
    assert corner(frames[-1], 2) == UNSOLVED_FRAME  # the longest ends unsolved on the last frame

    path = save_video(frames, tmp_path / "episodes.gif")
    with Image.open(path) as gif:  # Pillow merges identical neighbours, adding up their durations
        assert gif.size == (frames[0].shape[1], frames[0].shape[0])
        played_ms = 0
        for index in range(gif.n_frames):
            gif.seek(index)
            played_ms += gif.info["duration"]
        assert abs(played_ms - (STEPS + 1) * 1000 / 30) <= 10 * (STEPS + 1)  # GIF keeps hundredths of a second
    with pytest.raises(ValueError, match=r"write \.gif, \.webp or \.mp4"):
        save_video(frames, tmp_path / "episodes.avi")


def test_an_mp4_is_h264_yuv420p_padded_to_even_sizes_and_reads_back(episodes, tmp_path: Path) -> None:
    names, states, actuation, keep, solved = episodes
    frames = episode_grid_frames(states, actuation, keep, solved, names, scale=0.2, columns=3)
    odd = [frame[:99, :299] for frame in frames]  # 299 x 99: yuv420p needs even sides
    path = save_video(odd, tmp_path / "episodes.mp4", fps=30)
    with av.open(str(path)) as container:
        [stream] = container.streams.video
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        assert (stream.width, stream.height) == (300, 100) and stream.average_rate == 30
        decoded = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
    assert len(decoded) == len(odd) == STEPS + 1  # every frame kept, the held ones too
    for drawn, back in zip(odd, decoded, strict=True):
        assert back.shape == (100, 300, 3)
        error = np.abs(back[:99, :299].astype(int) - drawn.astype(int)).max(axis=-1)
        # Lossy, but close: H.264 and yuv420p's colour sampled per 2 x 2 pixels blur edges and text a little.
        assert error.mean() < 5 and np.percentile(error, 95) < 20 and (error > 48).mean() < 0.01
        assert back[99].mean() > 200 and back[:, 299].mean() > 200  # padded with white (blurred by the edge)
    tile = 100
    assert np.abs(decoded[1][2, tile + tile // 2].astype(int) - UNSOLVED_FRAME).max() < 30  # outcome frames survive
