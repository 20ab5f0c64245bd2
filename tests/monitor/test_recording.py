"""Rollouts in Rerun: a known short rollout logged to an .rrd file and read back with Rerun's own reader (entities,
component types, timelines, row counts, colours by role, the geometry the PNG renderer draws), the background
logger's promise: under load it drops rollouts instead of blocking, and with no viewer it logs nothing; and
`impulse view` coming and going during a run, or recording with no viewer at all (`--headless`)."""

from __future__ import annotations

import dataclasses
import functools
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from rerun.chunk import RrdReader

from impulse.actors.rollout import rollout, start_rollout
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.drawing import FIXED_NEUTRAL, ROLE_COLOURS, scene_drawing
from impulse.engine.levels.level import stack_levels
from impulse.engine.physics.sizes import SIZE_S
from impulse.monitor.draw import SCENE_PARTS
from impulse.monitor.metrics import log_scalars
from impulse.monitor.png import render_scene, world_to_pixel
from impulse.monitor.rollouts import RolloutFrames, contact_points, log_rollout
from impulse.monitor.stream import Monitor, open_recording
from tests.support.launch_procs import free_port, wait_for
from tests.support.monitor_scenes import small_level
from tests.support.paths import REPO

pytestmark = pytest.mark.heavy

SPEC = EnvSpec(sizes=SIZE_S, max_timesteps=4)  # an episode ends within the rollout
STEPS = 6
ENVS = 2
DRIVE = np.array([0, 1, 0, 0, 1, 0], np.int32)  # motor binding 1 forward, thruster binding 0 on
ENTITY = "/rollouts/actor-7/env-0"



def drive_policy(params, obs, key):
    num = jax.tree.leaves(obs)[0].shape[0]
    return jnp.broadcast_to(jnp.asarray(DRIVE), (num, DRIVE.size)), jnp.zeros(num), jnp.zeros(num)


@functools.cache
def played():
    """Six steps of two environments on the small level, driving its motor and thruster, the first one watched."""
    levels = stack_levels([small_level()])
    carry = start_rollout(SPEC, EnvParams(), levels, ENVS, jax.random.key(0))
    result = jax.jit(lambda c: rollout(drive_policy, None, SPEC, EnvParams(), c, levels, STEPS, watch=1))(carry)
    return jax.device_get(result)


def frames() -> RolloutFrames:
    steps, watched = played().steps, played().watched
    return RolloutFrames(
        source="actor-7", states=watched.state, actuation=watched.actuation, reward=steps.reward[:, :1],
        done=steps.done[:, :1], solved=steps.solved[:, :1], truncated=steps.truncated[:, :1],
        episode_return=steps.episode_return[:, :1], policy_version=3, first_step=100,
        episodes_before=np.array([5]), started_at=1.7e9, seconds=0.5, contacts=True)


def read_back(path) -> dict[str, list]:
    """Entity path -> its chunks, from the file as Rerun reads it."""
    reader = RrdReader(path)
    [store] = reader.recordings()
    assert (store.application_id, store.recording_id) == ("impulse", "run-a")
    chunks: dict[str, list] = {}
    for chunk in reader.stream().collect().stream():
        chunks.setdefault(chunk.entity_path, []).append(chunk)
    return chunks


def column(chunks: list, name: str) -> list:
    """All values of one column over an entity's chunks, rows in log order of each chunk."""
    values = []
    for chunk in chunks:
        batch = chunk.to_record_batch()
        matching = [n for n in batch.schema.names if n == name or n.endswith(f":{name}")]
        assert matching, (name, batch.schema.names)
        values += batch.column(matching[0]).to_pylist()
    return values


def packed(rgb) -> int:
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | 0xFF


def test_a_rollout_recorded_to_rrd_reads_back(tmp_path) -> None:
    path = tmp_path / "rollout.rrd"
    recording = open_recording("run-a", path=path)
    assert log_rollout(recording, frames()) == STEPS
    recording.flush()
    recording.disconnect()
    chunks = read_back(path)

    for part in (*SCENE_PARTS, "contacts"):
        assert sum(c.num_rows for c in chunks[f"{ENTITY}/scene/{part}"]) == STEPS, part
    assert sum(c.num_rows for c in chunks[f"{ENTITY}/reward"]) == STEPS
    for entity in (f"{ENTITY}/scene/polygons", f"{ENTITY}/reward"):
        for chunk in chunks[entity]:
            assert {"env_step", "episode", "episode_step", "wall"} <= set(chunk.timeline_names)
    assert column(chunks[f"{ENTITY}/reward"], "env_step") == list(range(100, 100 + STEPS))
    # The episode ends at the time limit (4 steps): episode 5 for steps 0..3, then episode 6 from its start.
    assert column(chunks[f"{ENTITY}/reward"], "episode_step") == [0, 1, 2, 3, 0, 1]
    assert column(chunks[f"{ENTITY}/reward"], "episode") == [5, 5, 5, 5, 6, 6]
    [[ended]] = column(chunks[f"{ENTITY}/episodes"], "TextLog:text")
    assert ended.startswith("episode 5 timed out") and "policy version 3" in ended
    assert len(column(chunks[f"{ENTITY}/info"], "TextDocument:text")) == 2  # logged when the episode changes

    schema_types = {c.to_record_batch().schema.field(n).metadata.get(b"rerun:component_type", b"").decode()
                    for cs in chunks.values() for c in cs for n in c.to_record_batch().schema.names}
    assert {"rerun.components.LineStrip2D", "rerun.components.Position2D", "rerun.components.Radius",
            "rerun.components.Color", "rerun.components.Vector2D", "rerun.components.Scalar",
            "rerun.components.Text"} <= schema_types

    # Colours by role: the green box and the fixed arena polygons; the red ball and the fixed (darker) blue one.
    polygon_colours = column(chunks[f"{ENTITY}/scene/polygons"], "LineStrips2D:colors")[0]
    assert polygon_colours.count(packed(ROLE_COLOURS[1])) == 1
    assert polygon_colours.count(packed(FIXED_NEUTRAL)) == 4 and len(polygon_colours) == 5
    circle_colours = column(chunks[f"{ENTITY}/scene/circles"], "Points2D:colors")[0]
    assert sorted(circle_colours) == sorted([packed(ROLE_COLOURS[3]), packed(tuple(c // 2 for c in ROLE_COLOURS[2]))])
    # Motors and thrusters: the driven joint is labelled with its command, the firing thruster has a flame.
    assert column(chunks[f"{ENTITY}/scene/joints"], "Points2D:labels")[0] == ["+1"]
    assert all(len(v) == 1 for v in column(chunks[f"{ENTITY}/scene/flames"], "Arrows2D:vectors"))


def test_the_png_renderer_draws_the_same_geometry(tmp_path) -> None:
    """The outlines Rerun got, back in world coordinates, enclose pixels of their own colour in the PNG."""
    path = tmp_path / "scene.rrd"
    recording = open_recording("run-a", path=path)
    log_rollout(recording, frames())
    recording.flush()
    recording.disconnect()
    chunks = read_back(path)
    strips = column(chunks[f"{ENTITY}/scene/polygons"], "LineStrips2D:strips")[-1]
    colours = column(chunks[f"{ENTITY}/scene/polygons"], "LineStrips2D:colors")[-1]
    last = jax.tree.map(lambda x: x[-1, 0], played().watched.state)
    image = render_scene(scene_drawing(last.level, last.sim))
    for strip, colour in zip(strips, colours, strict=True):
        world = np.asarray(strip)[:-1] * [1, -1] + [0, 5]  # the view's y is down
        centre = world.mean(axis=0)
        if not (0 < centre[0] < 5 and 0 < centre[1] < 5):
            continue  # arena walls outside the picture
        rgb = ((colour >> 24) & 255, (colour >> 16) & 255, (colour >> 8) & 255)
        assert tuple(image[world_to_pixel(*centre)]) == rgb


def test_contacts_are_where_shapes_touch() -> None:
    """The green box (0.8 x 0.6 m, centre x = 1.5) pushed 5 cm into the floor touches it along its bottom edge;
    in the level as built nothing touches (the red ball is hinged to the box: joined pairs do not count)."""
    level = small_level()
    floor_top = float(np.max(np.asarray(level.state.polygon_vertices)[0, :, 1]) + level.state.bodies.position[0, 1])
    box = 4  # the first polygon after the four arena ones
    sunk = level.state.bodies.position.copy()
    sunk[box, 1] = floor_top + 0.3 - 0.05
    sims = jax.tree.map(lambda a, b: np.stack([a, b]), level.state,
                        dataclasses.replace(level.state, bodies=dataclasses.replace(level.state.bodies,
                                                                                    position=sunk)))
    before, after = contact_points(sims)
    assert before.shape == (0, 2)
    assert 1 <= len(after) <= 2, after
    assert np.all(np.abs(after[:, 1] - floor_top) < 0.06) and np.all((after[:, 0] > 1.05) & (after[:, 0] < 1.95))


def test_the_logger_drops_rollouts_under_load_and_never_blocks(tmp_path) -> None:
    slow = frames()

    def slow_job(recording) -> int:
        time.sleep(0.2)  # a viewer far slower than the actor
        return log_rollout(recording, slow)

    with Monitor("run-a", path=tmp_path / "load.rrd", frame_queue=1, frames_per_s=1e6) as monitor:
        start = time.perf_counter()
        offered = [monitor.offer_frames(slow_job) for _ in range(20)]
        offering_s = time.perf_counter() - start
        assert offering_s < 0.1, "offering frames must not wait for the logger"
        assert offered.count(False) >= 17 and monitor.counts["rollouts_dropped"] == offered.count(False)
    assert monitor.counts["rollouts_logged"] == offered.count(True)
    assert monitor.counts["frames_logged"] == STEPS * offered.count(True)
    assert monitor.counts["no_viewer"] == 0


def test_with_no_viewer_nothing_is_logged_or_kept() -> None:
    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    with Monitor("run-a", url=url, probe_every_s=0.05) as monitor:
        time.sleep(0.3)  # a few probes
        assert not monitor.viewer_up and not monitor.wants_frames(STEPS)
        assert all(monitor.log(lambda recording: 0) for _ in range(5))
        time.sleep(0.2)
        assert monitor.counts["no_viewer"] == 5 and monitor.counts["records_logged"] == 0


def test_a_bad_url_is_refused_at_once() -> None:
    with pytest.raises(ValueError, match="not a Rerun gRPC url"):
        Monitor("run-a", url="http://127.0.0.1:9876/")


def processes_using(port: int) -> list[int]:
    """PIDs whose command line names `port` (Rerun servers left behind would show here)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            words = (entry / "cmdline").read_bytes().split(b"\0") if entry.name.isdigit() else []
        except OSError:
            continue
        if str(port).encode() in words and any(b"rerun" in w for w in words):
            found.append(int(entry.name))
    return found


def view(run_dir: Path, record: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "impulse.deploy.cli", "view", str(run_dir), "--web", "--record",
                             str(record)], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def rows_of(path: Path, entity: str) -> list[float]:
    return [v for c in RrdReader(path).stream().collect().stream() if c.entity_path == entity
            for row in c.to_record_batch().column("Scalars:scalars").to_pylist() for v in row]


def test_impulse_view_can_come_and_go_during_a_run(tmp_path) -> None:
    """A process streams before, during, between and after two `impulse view --record` sessions: each file holds
    what was logged while its viewer was up, nothing is kept for a viewer that is not there, and stopping the
    viewer leaves no Rerun server behind."""
    port = free_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    (tmp_path / "config.toml").write_text(f"name = 'come-and-go'\n[monitor]\nurl = '{url}'\nweb_port = "
                                          f"{free_port()}\n")
    values = iter(range(100))

    def log_five(monitor: Monitor) -> None:
        for _ in range(5):
            value = float(next(values))
            monitor.log(lambda rec, value=value: log_scalars(rec, "metrics/test", {"x": value}))
        time.sleep(0.5)

    with Monitor("come-and-go", url=url, probe_every_s=0.1) as monitor:
        log_five(monitor)  # 0..4: no viewer yet
        for record in (tmp_path / "first.rrd", tmp_path / "second.rrd"):
            viewer = view(tmp_path, record)
            wait_for(lambda: monitor.viewer_up, 30, "the monitor to see the viewer")
            log_five(monitor)  # 5..9, then 15..19
            time.sleep(1.0)
            viewer.send_signal(signal.SIGINT)
            assert viewer.wait(30) == 0
            assert processes_using(port) == []
            wait_for(lambda: not monitor.viewer_up, 30, "the monitor to see the viewer go")
            log_five(monitor)  # 10..14, then 20..24: the viewer is gone
        assert monitor.counts["no_viewer"] == 15 and monitor.counts["records_logged"] == 10
    assert rows_of(tmp_path / "first.rrd", "/metrics/test/x") == [5, 6, 7, 8, 9]
    assert rows_of(tmp_path / "second.rrd", "/metrics/test/x") == [15, 16, 17, 18, 19]


def test_impulse_view_headless_records_without_a_viewer(tmp_path) -> None:
    """`impulse view --headless --record FILE` (what `impulse launch --record FILE` starts without --view): one
    Rerun process, no viewer, is the server a process streams to, and the file holds the rollout and the curves
    it streamed; Ctrl-C ends it, leaving no Rerun server behind. Without --record it is refused."""
    port = free_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    (tmp_path / "config.toml").write_text(f"name = 'run-a'\n[monitor]\nurl = '{url}'\nweb_port = {free_port()}\n")
    refused = subprocess.run([sys.executable, "-m", "impulse.deploy.cli", "view", str(tmp_path), "--headless"],
                             cwd=REPO, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--record" in refused.stderr
    record = tmp_path / "headless.rrd"
    recorder = subprocess.Popen([sys.executable, "-m", "impulse.deploy.cli", "view", str(tmp_path), "--headless",
                                 "--record", str(record)], cwd=REPO, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    try:
        with Monitor("run-a", url=url, probe_every_s=0.1) as monitor:
            wait_for(lambda: monitor.viewer_up, 30, "the monitor to see the recording server")
            assert len(processes_using(port)) == 1  # one Rerun process: the server, recording; no viewer
            assert monitor.offer_frames(lambda recording: log_rollout(recording, frames()))
            for value in range(3):
                monitor.log(lambda recording, value=value: log_scalars(recording, "metrics/test", {"x": value}))
            wait_for(lambda: monitor.counts["rollouts_logged"] == 1 and monitor.counts["records_logged"] == 3, 30,
                     "the monitor to log")
        time.sleep(1.0)
    finally:
        recorder.send_signal(signal.SIGINT)
        assert recorder.wait(30) == 0
    assert processes_using(port) == []
    chunks = read_back(record)
    assert sum(c.num_rows for c in chunks[f"{ENTITY}/scene/polygons"]) == STEPS
    assert rows_of(record, "/metrics/test/x") == [0, 1, 2]
