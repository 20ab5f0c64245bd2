"""`impulse launch curriculum=sfl` on random levels with a deliberately slow learner (one launch, shared by three
checks to keep the suite short; real processes, real zenoh on loopback):

1. back pressure: an actor (configured to drop its oldest batch) keeps rolling out without flooding anything;
   drops are counted and every process's resident memory, the curriculum service's included, stays flat;
2. the curriculum: the launcher started it, actors train on the levels it serves and report results back, and a
   person retunes it while it runs with `impulse curriculum set` (a bad value refused, a good one taking effect
   at the next sample), reads it back with `get`, sends a level into its buffer with `inject` and looks at the
   buffer with `inspect`; and `impulse studio --run RUN_DIR`, as its own process, shows that buffer and its knobs,
   changes a knob and sends a level in over HTTP (the page's own requests), and its Curriculum page, in a headless
   chromium, shows the running service's buffer with thumbnails and changes a knob that the service then holds;
3. Ctrl-C stops the run in order: the learner's final checkpoint holds its last update and the curriculum
   service checkpoints its buffer;
4. `--record` without `--view`: every process streams to one Rerun recording (the run's name as its id) through
   the headless recording server the launcher started (no viewer), and the .rrd file holds the actors' rollouts,
   the learner's curves and the curriculum's histograms, gallery and knob change. The memory check above runs
   with the streaming on;
5. the evaluator the launcher started scores the learner's policies: the scores reach the learner's metrics.jsonl
   rows, the status display and the recording (the learner's and the evaluator's curves); the rows also carry the
   curriculum service's buffer statistics (`curriculum_...`, the fused trainer's columns)."""

from __future__ import annotations

import functools
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from urllib.parse import parse_qs, urlsplit

import numpy as np
import pytest
from rerun.chunk import RrdReader

from impulse.bus.codec import Kind, decode
from impulse.curriculum.state import ORIGIN_REPLAY
from impulse.curriculum.wire import level_batch_from_message, level_batch_schema, level_batch_template
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.engine.env.spec import EnvSpec
from impulse.learner.checkpoint import Checkpointer
from tests.support.browser import browser_page, missing_browser
from tests.support.launch_procs import (
    REPO,
    SMALL_BATCH,
    StatusWatcher,
    free_port,
    last_update,
    metrics,
    rss_mib,
    service_pids,
    start_launch,
    stop_launch,
    tail,
    wait_for,
)

pytestmark = pytest.mark.heavy

WATCH_S = 24.0
SAMPLE_S = 2.0
TREND_LIMIT_MIB = 48.0
"""The learner's resident memory swings by about 80 MiB within each update (one batch in flight, update
temporaries), so flatness is judged on peaks: the later half's peak may not exceed the earlier half's by more."""
ENVS = 32  # the batch of SMALL_BATCH
ACTORS = (0,)
"""One actor: an actor told to drop its oldest batch rolls out without pause, taking a core for the whole test, and
one shows the back pressure as well as two (each actor's credits are its own)."""


def curriculum_cli(run_dir, *words: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "impulse.deploy.cli", "curriculum", *words, "--run", str(run_dir)],
                          capture_output=True, text=True, timeout=120, cwd=REPO)


def check_memory_stays_flat(run_dir, watcher: StatusWatcher) -> None:
    pids = {"learner": service_pids(run_dir, "learner")[0], "curriculum": service_pids(run_dir, "curriculum")[0],
            **{f"actor-{i}": service_pids(run_dir, "actor", i)[0] for i in ACTORS}}
    drops_before = sum(watcher.poll().get(f"actor-{i}", {}).get("dropped_no_credit", 0) for i in ACTORS)
    samples: dict[str, list[float]] = {name: [] for name in pids}
    for _ in range(int(WATCH_S / SAMPLE_S)):
        for name, pid in pids.items():
            samples[name].append(rss_mib(pid))
        time.sleep(SAMPLE_S)
    statuses = watcher.poll()
    half = len(samples["learner"]) // 2
    before = {name: max(values[:half]) for name, values in samples.items()}
    after = {name: max(values[half:]) for name, values in samples.items()}
    for name in pids:
        assert after[name] - before[name] < TREND_LIMIT_MIB, (name, samples[name])
    drops = sum(statuses[f"actor-{i}"]["dropped_no_credit"] for i in ACTORS)
    assert drops - drops_before >= 3, f"actors should have replaced held-back batches: {statuses}"
    assert all(statuses[f"actor-{i}"]["in_flight"] <= 1 for i in ACTORS), statuses
    assert statuses["learner"]["queue"] <= 2, statuses["learner"]
    print(f"peak RSS MiB, first half {before}, second half {after}; batches dropped by actors {drops}")


def check_live_curriculum(run_dir, watcher: StatusWatcher, tmp_path) -> None:
    got = curriculum_cli(run_dir, "get")
    assert got.returncode == 0 and "method = sfl" in got.stdout and "sfl_ratio = 0.5" in got.stdout, got

    refused = curriculum_cli(run_dir, "set", "sfl_ratio=7")
    assert refused.returncode == 2 and "sfl_ratio must be in [0, 1]" in refused.stderr, refused

    changed = curriculum_cli(run_dir, "set", "curriculum.sfl_ratio=1.0", "min_fill=0")
    assert changed.returncode == 0 and "sfl_ratio: 0.5 -> 1.0" in changed.stdout, changed
    service_log = run_dir / "logs" / "curriculum.log"
    wait_for(lambda: "curriculum knob sfl_ratio: 0.5 -> 1.0" in service_log.read_text(), 10,
             "the service to log the change")

    # The next batch an actor asks for comes wholly from the buffer.
    template = level_batch_template(EnvSpec().sizes, ENVS)
    [payload] = watcher.bus.get(watcher.bus.keys.levels_sample, parameters=f"n={ENVS}", timeout_s=30)
    batch = level_batch_from_message(decode(payload, run=run_dir.name, kinds=Kind.LEVELS),
                                     level_batch_schema(template), template)
    assert (np.asarray(batch.origin) == ORIGIN_REPLAY).all()

    # A level a person sends in (`impulse curriculum inject`) enters the running service's buffer.
    car = REPO / "engine" / "levels" / "handmade" / "s_easy_car_right.json"
    injected = curriculum_cli(run_dir, "inject", str(car))
    assert injected.returncode == 0 and "s_easy_car_right.json: level " in injected.stdout, injected
    assert "in buffer slot" in injected.stdout
    wait_for(lambda: watcher.poll().get("curriculum", {}).get("injected") == 1, 10, "the service to count it")

    inspected = curriculum_cli(run_dir, "inspect", "--json", "--top", "3", "--render", str(tmp_path / "top"))
    assert inspected.returncode == 0, inspected.stderr
    report = json.loads(inspected.stdout[inspected.stdout.index("{"):])
    assert report["method"] == "sfl" and report["knobs"]["sfl_ratio"] == 1.0
    assert 0 < len(report["top"]) <= 3 and report["summary"]["buffer_fill"] > 0
    assert len(list((tmp_path / "top").glob("*.png"))) == len(report["top"])


def studio_request_with(base: str, path: str, body: dict | None = None, token: str = "") -> tuple[int, dict | bytes]:
    """(status, JSON reply or raw bytes) of one request to a studio, as its page makes them (with the studio's
    per-start `token`)."""
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(base + path, data=data, headers={"Content-Type": "application/json",
                                                                     "X-Impulse-Token": token})
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            status, raw, kind = response.status, response.read(), response.headers.get_content_type()
    except urllib.error.HTTPError as err:
        status, raw, kind = err.code, err.read(), err.headers.get_content_type()
    return status, (json.loads(raw) if kind == "application/json" else raw)


def check_studio_console(run_dir, watcher: StatusWatcher, tmp_path) -> None:
    """`impulse studio --run RUN_DIR` (its own process) linked to the launched run's curriculum service."""
    port = free_port()
    log_path = tmp_path / "studio.log"
    command = [sys.executable, "-m", "impulse.deploy.cli", "studio", "--run", str(run_dir), "--port", str(port),
               "--levels-dir", str(tmp_path / "studio-levels")]
    env = {**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache"), "PYTHONUNBUFFERED": "1"}
    with log_path.open("wb") as out:
        studio = subprocess.Popen(command, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_for(lambda: "Impulse Studio: open" in log_path.read_text(), 60, "the studio to start", studio, log_path)
        url = re.search(r"open (\S+)", log_path.read_text()).group(1)  # the printed address, with its token
        token = parse_qs(urlsplit(url).query)["token"][0]
        studio_request = functools.partial(studio_request_with, token=token)
        deadline = time.monotonic() + 30
        while True:
            try:
                status, agents = studio_request(base, "/api/agents")
                break
            except OSError:
                assert time.monotonic() < deadline, tail(log_path)
                time.sleep(0.2)
        assert status == 200 and agents["inject_run"] == run_dir.name, agents

        status, page = studio_request(base, "/api/curriculum?top=3")
        assert status == 200 and page["run"] == run_dir.name and page["knobs"]["sfl_ratio"] == 1.0, page
        assert 0 < len(page["top"]) <= 3, page["top"]
        status, png = studio_request(base, f"/api/curriculum/thumbnail?level_id={page['top'][0]['level_id']}")
        assert status == 200 and png.startswith(b"\x89PNG")

        status, reply = studio_request(base, "/api/curriculum/knobs", {"set": ["sfl_ratio=7"]})
        assert status == 422 and "sfl_ratio must be in [0, 1]" in reply["error"], reply
        status, reply = studio_request(base, "/api/curriculum/knobs", {"set": ["sfl_ratio=0.5"]})
        assert status == 200 and "sfl_ratio" in reply["changed"], reply
        got = curriculum_cli(run_dir, "get")  # the service's own answer
        assert got.returncode == 0 and "sfl_ratio = 0.5" in got.stdout, got

        check_curriculum_page(url, run_dir)

        thrust = REPO / "engine" / "levels" / "handmade" / "s_easy_thrust_right.json"
        status, reply = studio_request(base, "/api/inject", {"level": json.loads(thrust.read_text())})
        assert status == 200 and reply["ok"] and "slot" in reply, reply
        wait_for(lambda: watcher.poll().get("curriculum", {}).get("injected") == 2, 10, "the service to count it")
    finally:
        studio.send_signal(signal.SIGINT)
        try:
            studio.wait(timeout=20)
        except subprocess.TimeoutExpired:
            studio.kill()


def check_curriculum_page(url: str, run_dir) -> None:
    """The studio's Curriculum page in a real browser, against the launched run's service: the buffer table with a
    thumbnail per level, and a knob changed from the page, which the service then reports."""
    reason = missing_browser()
    if reason is not None:
        print(f"the Curriculum page was not driven in a browser: {reason}")
        return
    with browser_page(url) as page:
        page.wait_for_function("!document.getElementById('tab-curriculum').hidden")
        page.click("#tab-curriculum")
        page.wait_for_function("document.querySelectorAll('#curriculum-table tbody tr').length > 0")
        page.wait_for_function("[...document.querySelectorAll('#curriculum-table img')]"
                               ".every(i => i.complete && i.naturalWidth > 0)")
        rows = page.locator("#curriculum-table tbody tr").count()
        assert page.locator("#curriculum-table img").count() >= rows
        assert page.locator("#knob-sfl_ratio").input_value() == "0.5"
        page.fill("#knob-sfl_ratio", "0.75")
        page.click("#curriculum-apply")
        page.wait_for_function("document.getElementById('message').textContent.startsWith('changed sfl_ratio')")
    got = curriculum_cli(run_dir, "get")  # the service's own answer
    assert got.returncode == 0 and "sfl_ratio = 0.75" in got.stdout, got


def check_recording(path, run: str) -> None:
    """The .rrd the recording server wrote: one recording of the run, with what every process streamed."""
    reader = RrdReader(path)
    assert [(s.application_id, s.recording_id) for s in reader.recordings()] == [("impulse", run)]
    rows: dict[str, int] = {}
    knob_lines: list[str] = []
    for chunk in reader.stream().collect().stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
        if chunk.entity_path == "/curriculum/knob_changes":
            knob_lines += [line for row in chunk.to_record_batch().column("TextLog:text").to_pylist() for line in row]
    for actor in (f"actor-{i}" for i in ACTORS):
        assert rows.get(f"/rollouts/{actor}/env-0/scene/polygons", 0) >= 32, (actor, sorted(rows))
        assert rows.get(f"/metrics/{actor}/steps_per_s", 0) >= 2
    assert rows.get("/metrics/learner/total_loss", 0) >= 3 and rows.get("/metrics/learner/window/solve_rate", 0)
    assert rows.get("/metrics/learner/status/consumed_steps_per_s", 0) >= 2
    assert rows.get("/curriculum/histograms/score", 0) >= 1 and rows.get("/curriculum/stats/buffer_fill", 0) >= 1
    assert rows.get("/curriculum/top/0/scene/polygons", 0) >= 1
    assert rows.get("/metrics/learner/eval/mean", 0) >= 1 and rows.get("/metrics/evaluator/eval/mean", 0) >= 1, (
        sorted(name for name in rows if "eval" in name))
    assert "sfl_ratio: 0.5 -> 1.0" in knob_lines, knob_lines


def test_slow_learner_back_pressure_live_curriculum_and_ctrl_c_checkpoints(tmp_path):
    run_dir = tmp_path / "slow"
    port = free_port()
    recording = tmp_path / "run.rrd"
    launch, log = start_launch(run_dir, port, *SMALL_BATCH, "learner.slow_down_s=1.5",
                               f"actors.num_actors={len(ACTORS)}", "actors.when_no_credit=drop_oldest",
                               "actors.credits=1", "total_env_steps=40960000", "checkpoint.every_updates=1000",
                               "env.levels=random", "curriculum=sfl", "curriculum.buffer_size=32",
                               "curriculum.candidate_episodes=1", "curriculum.noop_filter=false",
                               "--record", str(recording), "monitor.curriculum_every_s=2",
                               "evaluator.levels=handmade:s_easy_car_right", "evaluator.every_updates=2",
                               "evaluator.attempts=2",
                               f"monitor.url=rerun+http://127.0.0.1:{free_port()}/proxy",
                               f"monitor.web_port={free_port()}")
    watcher = StatusWatcher(run_dir.name, port)
    try:
        wait_for(lambda: last_update(run_dir) >= 3, 400, "the first updates", launch, log)
        check_memory_stays_flat(run_dir, watcher)

        curriculum = lambda: watcher.poll().get("curriculum", {})  # noqa: E731
        wait_for(lambda: curriculum().get("results", 0) >= 2 and curriculum().get("buffer_fill", 0) > 0, 120,
                 "the curriculum to receive results and keep a level", launch, log)
        check_live_curriculum(run_dir, watcher, tmp_path)
        check_studio_console(run_dir, watcher, tmp_path)
        # The evaluator scores the learner's policies; the learner writes the scores into its metrics rows.
        wait_for(lambda: watcher.poll().get("learner", {}).get("evaluation", {}).get("policy_version") is not None
                 and any("eval/level/s_easy_car_right" in row for row in metrics(run_dir)), 180,
                 "an evaluation in the learner's metrics", launch, log)
        # The learner's rows also carry the curriculum service's buffer statistics, as the fused trainer's do.
        wait_for(lambda: any(row.get("curriculum_buffer_fill", 0) > 0 and row.get("curriculum_count_inserted", 0) >= 1
                             for row in metrics(run_dir)), 60, "the curriculum's statistics in the learner's metrics",
                 launch, log)

        # Ctrl-C: actors stop first, then the curriculum and the learner checkpoint and exit.
        launch.send_signal(signal.SIGINT)
        assert launch.wait(timeout=240) == 0, tail(log)
    finally:
        watcher.close()
        stop_launch(launch, run_dir, ("learner", "actor", "curriculum", "view"))
    config = resolve_config(RunConfig, run_dir / "config.toml")
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        assert checkpoints.latest_step() == last_update(run_dir), "the final checkpoint holds the last update"
    assert not any(service_pids(run_dir, role) for role in ("learner", "actor", "curriculum"))
    assert "stopping the learner" in log.read_text()
    assert "curriculum stopped" in (run_dir / "logs" / "curriculum.log").read_text()
    assert f"learner stopped at update {last_update(run_dir)} of" in (run_dir / "logs" / "learner.log").read_text()
    assert any((run_dir / "curriculum" / "checkpoints").iterdir()), "the service checkpointed its buffer"
    assert f"recording what the processes stream to {recording} (no viewer" in log.read_text()
    assert "no viewer for run slow: a Rerun server at" in (run_dir / "logs" / "viewer.log").read_text()
    assert "| scored v" in log.read_text(), "the status display shows the evaluator's scores"
    check_recording(recording, run_dir.name)
