"""`impulse levels`: validate (exit codes, every problem printed), show, render (PNG of the scene, or a video of
levels played with no-op actions) and convert; files that are not level files (binary, empty, cut short, a folder)
give one line naming the file, never a traceback."""

from __future__ import annotations

import json
from pathlib import Path

import av
import jax
import numpy as np
import pytest
from PIL import Image

from impulse.deploy.cli import main
from impulse.engine.levels.drawing import ROLE_COLOURS
from impulse.engine.levels.kinetix_json import level_to_json_dict, load_kinetix_level, save_kinetix_level
from impulse.engine.levels.level import level_from_scene
from impulse.engine.physics.building import empty_scene
from impulse.engine.physics.sizes import SIZE_M, SIZE_S
from impulse.monitor.png import world_to_pixel
from impulse.monitor.video import BORDER, UNSOLVED_FRAME
from tests.support.bad_level_files import write_bad_inputs
from tests.support.monitor_scenes import BLUE_AT, GREEN_AT, small_level
from tests.support.paths import REPO


@pytest.fixture(scope="module")
def level_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_kinetix_level(tmp_path_factory.mktemp("levels") / "small.json", small_level(), SIZE_S)


def write_bad(path: Path) -> Path:
    data = level_to_json_dict(small_level(), SIZE_S)
    del data["env_state"]["polygon"][4]["velocity"]
    data["env_state"]["circle"][0]["role"] = 5
    path.write_text(json.dumps(data))
    return path


def test_validate_reports_every_problem_and_exit_code(
    tmp_path: Path, level_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["levels", "validate", str(level_file)]) == 0
    out = capsys.readouterr().out
    assert f"ok       {level_file}" in out and "1 of 1 level files valid" in out

    folder = tmp_path / "set"
    folder.mkdir()
    (folder / "good.json").write_text(level_file.read_text())
    bad = write_bad(folder / "bad.json")
    (folder / "notes.txt").write_text("not a level")
    assert main(["levels", "validate", str(folder)]) == 1
    out = capsys.readouterr().out
    assert f"INVALID  {bad}" in out and f"ok       {folder / 'good.json'}" in out
    assert "polygon[4].velocity missing" in out and "circle[0].role: 5 is not a role" in out
    assert "1 of 2 level files valid" in out and "notes.txt" not in out

    assert main(["levels", "validate", str(level_file), "--size", "m"]) == 0
    capsys.readouterr()
    empty_m = level_from_scene(jax.jit(empty_scene, static_argnums=0)(SIZE_M))
    m_file = save_kinetix_level(tmp_path / "m.json", empty_m, SIZE_M)
    assert main(["levels", "validate", str(m_file), "--size", "s"]) == 1
    assert "too large for the size" in capsys.readouterr().out
    assert main(["levels", "validate", str(tmp_path / "absent.json")]) == 1
    assert "no such file" in capsys.readouterr().out


def test_show_describes_roles_links_and_controls(level_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["levels", "show", str(level_file)]) == 0
    out = capsys.readouterr().out
    assert "size: S; in use: 5 polygons incl. 4 arena, 2 circles, 1 joint, 1 thruster" in out
    assert "#4  green   rectangle 0.80 x 0.60 m, at (1.50, 2.50)" in out
    assert "blue    circle r 0.30 m" in out and "fixed" in out
    assert "red     circle r 0.20 m" in out
    assert "joint 0: revolute, green polygon #4 - red circle #6" in out and "motor binding 1" in out
    assert "motor action 1: joint 0" in out and "motor action 0: nothing" in out
    assert "thruster action 0: fires thruster 0 on green polygon #4" in out
    assert "task: make a green shape touch a blue shape without any green shape touching a red one" in out

    assert main(["levels", "show", str(level_file), "--size", "l"]) == 0
    out = capsys.readouterr().out
    assert "in the file, loaded as L" in out and "red circle #13" in out  # circles moved up by 7 polygon slots


def test_render_draws_the_scene(tmp_path: Path, level_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_png = tmp_path / "pictures" / "small.png"
    assert main(["levels", "render", str(level_file), "-o", str(out_png)]) == 0
    assert "500 x 500" in capsys.readouterr().out
    image = np.asarray(Image.open(out_png).convert("RGB"))
    assert image.shape == (500, 500, 3)
    green = tuple(ROLE_COLOURS[1])
    assert tuple(image[world_to_pixel(*GREEN_AT)]) == green
    # y points up: the green box is in the upper half at x = 1.5 m, and nowhere near the bottom-left.
    rows, cols = np.nonzero(np.all(image == green, axis=-1))
    assert abs(rows.mean() - (500 - GREEN_AT[1] * 100)) < 3 and abs(cols.mean() - GREEN_AT[0] * 100) < 3
    assert 0.75 * 80 * 60 < rows.size <= 80 * 60  # about the box's area (the outline and thruster take a little)
    # The blue ball is fixed, so it is drawn half as bright; the floor (neutral, fixed) dark grey at the bottom.
    below_centre = (BLUE_AT[0], BLUE_AT[1] - 0.15)  # off the line that marks the rotation
    assert tuple(image[world_to_pixel(*below_centre)]) == tuple(c // 2 for c in ROLE_COLOURS[2])
    assert tuple(image[world_to_pixel(2.5, 0.2)]) == (80, 80, 80)
    assert tuple(image[world_to_pixel(2.5, 4.0)]) == (255, 255, 255)

    half = tmp_path / "half.png"
    assert main(["levels", "render", str(level_file), "-o", str(half), "--scale", "0.5"]) == 0
    small = np.asarray(Image.open(half).convert("RGB"))
    assert small.shape == (250, 250, 3)
    assert tuple(small[world_to_pixel(*GREEN_AT, scale=0.5)]) == green


def test_render_video_plays_levels_with_no_op_actions(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two hand-made S levels side by side (200-pixel tiles, the default) for 12 no-op steps: the lander's green
    ball falls (the level's own dynamics), both episodes time out unsolved and are framed red on the last of the 13
    frames. A format other than .gif, .webp or .mp4 is refused before anything plays; a PNG draws one file."""
    handmade = REPO / "engine" / "levels" / "handmade"
    video = tmp_path / "levels.mp4"
    assert main(["levels", "render", str(handmade / "s_lander.json"), str(handmade / "s_hop_over.json"),
                 "--video", str(video), "--steps", "12"]) == 0
    assert "2 levels played with no-op actions for up to 12 steps (size S)" in capsys.readouterr().out
    with av.open(str(video)) as container:
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    assert len(frames) == 13 and frames[0].shape == (200, 400, 3)  # two 200-pixel tiles, a frame per step + 1

    def green_rows(frame: np.ndarray) -> float:  # mean row of the lander tile's green pixels (y down)
        tile = frame[BORDER + 12:, BORDER:200 - BORDER].astype(int)  # below the name
        rows, _ = np.nonzero(np.abs(tile - ROLE_COLOURS[1]).max(axis=-1) < 40)
        assert rows.size > 5
        return rows.mean()

    assert green_rows(frames[11]) > green_rows(frames[0]) + 5  # falling: gravity, no thrust
    for k in (0, 1):
        assert np.abs(frames[-1][BORDER // 2, k * 200 + 100].astype(int) - UNSOLVED_FRAME).max() < 40
        assert np.abs(frames[-2][BORDER // 2, k * 200 + 100].astype(int) - UNSOLVED_FRAME).max() > 40

    assert main(["levels", "render", str(handmade / "s_lander.json"), "--video", str(tmp_path / "x.avi")]) == 2
    assert ".gif, .webp or .mp4" in capsys.readouterr().err and not (tmp_path / "x.avi").exists()
    assert main(["levels", "render", str(handmade / "s_lander.json"), str(handmade / "s_hop_over.json"), "-o",
                 str(tmp_path / "two.png")]) == 2
    assert "--video plays several" in capsys.readouterr().err


def test_convert_resizes_and_loads_at_the_new_size(
    tmp_path: Path, level_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "as_m.json"
    assert main(["levels", "convert", str(level_file), str(target), "--size", "m"]) == 0
    assert "size M" in capsys.readouterr().out
    converted = load_kinetix_level(target)
    assert converted.sizes == SIZE_M
    original = load_kinetix_level(level_file)
    # The red circle (body 6 in S) is body 7 in M, still hinged to the green box.
    assert np.array_equal(np.asarray(converted.state.bodies.position)[7], np.asarray(original.state.bodies.position)[6])
    assert int(converted.state.joints.b_index[0]) == 7 and int(converted.level.roles[7]) == 3
    data = json.loads(target.read_text())
    assert data["static_env_params"]["num_polygons"] == 6 and len(data["env_state"]["circle"]) == 3

    assert main(["levels", "convert", str(target), str(tmp_path / "back.json"), "--size", "s"]) == 1
    err = capsys.readouterr().err
    assert "as_m.json" in err and "too large for the size" in err
    assert not (tmp_path / "back.json").exists()


def test_bad_input_and_usage(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = write_bad(tmp_path / "bad.json")
    assert main(["levels", "show", str(bad)]) == 1
    assert "polygon[4].velocity missing" in capsys.readouterr().err
    assert main(["levels", "render", str(bad), "-o", str(tmp_path / "x.png")]) == 1
    assert not (tmp_path / "x.png").exists()
    capsys.readouterr()
    assert main(["levels"]) == 2
    assert "choose an action" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["levels", "convert", str(bad), str(tmp_path / "y.json")])  # --size is required
    assert info.value.code == 2


BAD_INPUTS = ("latin-1 text", "random bytes", "PNG image", "empty file", "truncated JSON", "UTF-16 text", "folder")


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_every_action_names_a_bad_file_without_a_traceback(
    tmp_path: Path, case: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path, expected = write_bad_inputs(tmp_path / "bad")[case]
    outputs = tmp_path / "out.png", tmp_path / "out.json"
    for action in (["show", str(path)], ["render", str(path), "-o", str(outputs[0])],
                   ["convert", str(path), str(outputs[1]), "--size", "m"]):
        assert main(["levels", *action]) == 1, action  # an exception would fail the test here
        captured = capsys.readouterr()
        # The slow actions' heartbeat says first what they do (a log line); then the one error line.
        line = "\n".join(x for x in captured.err.strip().splitlines() if "impulse.deploy.runtime.progress:" not in x)
        assert line.startswith(f"impulse levels: {path}: ") and "\n" not in line, (action, line)
        assert all(part in line for part in expected), (action, expected, line)
        assert "Traceback" not in captured.err + captured.out
    assert not any(output.exists() for output in outputs)
    if path.is_file():  # a folder given to validate is searched for level files instead
        assert main(["levels", "validate", str(path)]) == 1
        out = capsys.readouterr().out
        lines = out.splitlines()
        assert lines[0] == f"INVALID  {path}" and all(part in lines[1] for part in expected), out
        assert lines[2] == "0 of 1 level files valid"


def test_validate_a_folder_with_one_bad_file(
    tmp_path: Path, level_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "set"
    (folder / "inner").mkdir(parents=True)
    (folder / "good.json").write_text(level_file.read_text())
    written = write_bad_inputs(tmp_path / "bad")
    bad = folder / "inner" / "random.json"
    bad.write_bytes(written["random bytes"][0].read_bytes())
    (folder / "inner" / "folder.json").mkdir()  # named like a level file, skipped
    assert main(["levels", "validate", str(folder)]) == 1
    out = capsys.readouterr().out
    assert f"ok       {folder / 'good.json'}" in out and f"INVALID  {bad}\n    not a UTF-8 text file (byte 0x" in out
    assert "folder.json" not in out and "1 of 2 level files valid" in out
    assert main(["levels", "validate", str(tmp_path / "bad" / "a_folder.json")]) == 1  # an empty folder
    out = capsys.readouterr().out
    assert "a_folder.json: no .json files in this folder" in out and "1 paths with no level file" in out
