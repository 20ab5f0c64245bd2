"""`impulse launch curriculum=sfl` on random levels: the launcher starts the curriculum service with the learner and
the actors, actors train on the levels it serves and report results back, and a person retunes it while it runs
with `impulse curriculum set` (a bad value refused, a good one taking effect at the next sample), reads it back
with `get` and looks at its buffer with `inspect`. Real processes, real zenoh on loopback."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import numpy as np
from launch_procs import REPO, StatusWatcher, free_port, start_launch, stop_launch, tail, wait_for

from bus.codec import Kind, decode
from curriculum.state import ORIGIN_REPLAY
from curriculum.wire import level_batch_from_message, level_batch_schema, level_batch_template
from engine.env.spec import EnvSpec

ENVS, STEPS = 16, 32
UPDATES = 1000  # more than the test waits for: it stops the run with SIGTERM, as Ctrl-C would


def curriculum_cli(run_dir, *words: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "deploy.cli", "curriculum", *words, "--run", str(run_dir)],
                          capture_output=True, text=True, timeout=120, cwd=REPO)


def test_launch_sfl_with_a_live_knob_change(tmp_path):
    run_dir = tmp_path / "sfl"
    port = free_port()
    launch, log = start_launch(
        run_dir, port, "env.levels=random", "curriculum=sfl", "curriculum.buffer_size=32",
        "curriculum.candidate_episodes=1", "curriculum.noop_filter=false", f"ppo.num_envs={ENVS}",
        f"ppo.num_steps={STEPS}", "ppo.num_minibatches=2", "ppo.update_epochs=2", "eval.attempts=0",
        f"total_env_steps={UPDATES * ENVS * STEPS}", "checkpoint.every_updates=10")
    watcher = StatusWatcher(run_dir.name, port)
    try:
        def curriculum_status():
            return watcher.poll().get("curriculum", {})

        wait_for(lambda: curriculum_status().get("results", 0) >= 2 and curriculum_status().get("buffer_fill", 0) > 0,
                 400, "the curriculum to receive results and keep a level", launch, log)

        got = curriculum_cli(run_dir, "get")
        assert got.returncode == 0 and "method = sfl" in got.stdout and "sfl_ratio = 0.5" in got.stdout, got

        refused = curriculum_cli(run_dir, "set", "sfl_ratio=7")
        assert refused.returncode == 2 and "sfl_ratio must be in [0, 1]" in refused.stderr, refused

        changed = curriculum_cli(run_dir, "set", "curriculum.sfl_ratio=1.0", "min_fill=0")
        assert changed.returncode == 0 and "sfl_ratio: 0.5 -> 1.0" in changed.stdout, changed
        wait_for(lambda: "curriculum knob sfl_ratio: 0.5 -> 1.0" in (run_dir / "logs" / "curriculum.log").read_text(),
                 10, "the service to log the change")

        # The next batch an actor asks for comes wholly from the buffer.
        template = level_batch_template(EnvSpec().sizes, ENVS)
        [payload] = watcher.bus.get(watcher.bus.keys.levels_sample, parameters=f"n={ENVS}", timeout_s=30)
        batch = level_batch_from_message(decode(payload, run=run_dir.name, kinds=Kind.LEVELS),
                                         level_batch_schema(template), template)
        assert (np.asarray(batch.origin) == ORIGIN_REPLAY).all()

        inspected = curriculum_cli(run_dir, "inspect", "--json", "--top", "3", "--render", str(tmp_path / "top"))
        assert inspected.returncode == 0, inspected.stderr
        report = json.loads(inspected.stdout[inspected.stdout.index("{"):])
        assert report["method"] == "sfl" and report["knobs"]["sfl_ratio"] == 1.0
        assert 0 < len(report["top"]) <= 3 and report["summary"]["buffer_fill"] > 0
        assert len(list((tmp_path / "top").glob("*.png"))) == len(report["top"])

        launch.send_signal(signal.SIGTERM)
        assert launch.wait(timeout=180) == 0, tail(log)
    finally:
        watcher.close()
        stop_launch(launch, run_dir)
    log_text = (run_dir / "logs" / "curriculum.log").read_text()
    assert "curriculum stopped" in log_text, tail(run_dir / "logs" / "curriculum.log")
    assert any((run_dir / "curriculum" / "checkpoints").iterdir()), "the service checkpointed its buffer"
