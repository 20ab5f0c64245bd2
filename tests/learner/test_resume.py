"""`impulse train curriculum=sfl` on random levels, killed with SIGKILL mid-training, its newest checkpoint then
damaged (a data file cut short), resumes from the checkpoint before it (the damaged one set aside, kept) and ends
with exactly the parameters, environments and curriculum buffer of a run that was never interrupted (real
`impulse train` processes, real orbax checkpoints with the `curriculum` item). The finished run's buffer is then
read back by `impulse curriculum inspect --checkpoint`, with no service running."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from impulse.deploy.cli import main
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.learner.checkpoint import Checkpointer
from impulse.learner.run import build, fused_checkpoint_items
from impulse.monitor.scalars import event_files
from tests.support.checkpoint_damage import corrupt_newest
from tests.support.paths import REPO
from tests.support.scalars import expected_points, metrics_rows, tensorboard_points

pytestmark = pytest.mark.heavy


QUICK = REPO / "configs" / "quick-cpu.toml"
UPDATES = 8
# The README's quick learner on random levels with a small SFL curriculum, at a quarter of its batch (32 envs x
# 32 steps), stopped after 8 updates, checkpointing every 2, without the final evaluation.
SETTINGS = ["--config", str(QUICK), f"total_env_steps={UPDATES * 32 * 32}", "ppo.num_envs=32", "ppo.num_steps=32",
            "ppo.num_minibatches=2", "checkpoint.every_updates=2",
            "checkpoint.keep_last=2", "eval.attempts=0", "env.levels=random", "curriculum=sfl",
            "curriculum.buffer_size=32", "curriculum.candidate_episodes=2", "curriculum.min_fill=0",
            "curriculum.noop_filter=false"]


def _train(run_dir: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache")}
    command = [
        sys.executable,
        "-c",
        "from impulse.deploy.cli import main; raise SystemExit(main())",
        "train",
        f"run_dir={run_dir}",
        *SETTINGS,
        *extra,
    ]
    return subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _carry_template(run_dir: Path):
    """The run's fused carry as shapes (the straight and the resumed run have the same)."""
    config = resolve_config(RunConfig, run_dir / "config.toml")
    trainer, _, _, levels = build(config)
    return jax.eval_shape(trainer.init, jax.random.PRNGKey(config.seed), levels)


def _final_params(run_dir: Path, template):
    config = resolve_config(RunConfig, run_dir / "config.toml")
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        assert checkpoints.latest_step() == UPDATES
        items, counters, _, _ = checkpoints.restore(fused_checkpoint_items(template))
    assert counters["update"] == UPDATES
    return items


def test_kill_9_then_resume_matches_an_uninterrupted_run(tmp_path, capsys):
    # One run straight through first: it also fills the compilation cache that the next two processes reuse.
    straight = _train(tmp_path / "straight")
    straight_out, _ = straight.communicate(timeout=400)
    assert straight.returncode == 0, straight_out
    killed_dir = tmp_path / "killed"
    victim = _train(killed_dir)
    # Kill it as soon as its second checkpoint is complete (orbax renames a finished step into place).
    deadline = time.monotonic() + 400
    while not (killed_dir / "checkpoints" / "4").is_dir():
        assert victim.poll() is None, f"training exited early:\n{victim.stdout.read()}"
        assert time.monotonic() < deadline, "no checkpoint within the time limit"
        time.sleep(0.05)
    victim.send_signal(signal.SIGKILL)
    victim.wait()
    assert victim.returncode == -signal.SIGKILL
    assert not (killed_dir / "checkpoints" / str(UPDATES)).exists(), "the victim finished before it was killed"
    damaged = corrupt_newest(killed_dir / "checkpoints", "train")
    assert damaged is not None and damaged >= 4

    resumed = _train(killed_dir, "--resume", str(killed_dir))
    resumed_out, _ = resumed.communicate(timeout=400)
    assert resumed.returncode == 0, resumed_out
    assert f"resumed from checkpoint {damaged - 2} " in resumed_out, resumed_out
    assert (killed_dir / "checkpoints-corrupt" / str(damaged)).is_dir()

    template = _carry_template(tmp_path / "straight")
    a, b = _final_params(tmp_path / "straight", template), _final_params(killed_dir, template)
    assert set(a) == {"train", "envs", "curriculum"}
    for left, right in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(left), np.asarray(right))
    records = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["curriculum_count_inserted"] > 0 and max(r["levels_replay"] for r in records) > 0, (
        "the SFL buffer filled and was replayed from")
    curriculum = a["curriculum"]
    filled = np.asarray(curriculum.buffer.filled)
    solved = np.asarray(curriculum.buffer.solved)[filled]
    assert (solved > 0).all(), "SFL keeps no level its policy never solved"
    # Every update appears in the resumed run's metrics, the recomputed ones after the kill included.
    lines = (killed_dir / "metrics.jsonl").read_text().splitlines()
    assert len(lines) >= UPDATES
    # TensorBoard shows what the rewound metrics.jsonl holds, each step once: the resumed process's event file hid
    # the victim's points past the checkpoint it resumed from.
    assert len(event_files(killed_dir / "tensorboard")) == 2
    points, _ = tensorboard_points(killed_dir / "tensorboard")
    assert points == expected_points(metrics_rows(killed_dir / "metrics.jsonl"))

    # A finished fused run's buffer, read from its newest checkpoint without any service.
    top = tmp_path / "top"
    assert main(["curriculum", "inspect", "--run", str(tmp_path / "straight"), "--checkpoint", "--json", "--top", "3",
                 "--render", str(top)]) == 0
    out = capsys.readouterr().out
    report = json.loads(out[out.index("{"):])
    assert report["checkpoint"]["step"] == UPDATES and report["method"] == "sfl"
    assert report["summary"]["buffer_fill"] == pytest.approx(filled.mean())
    assert len(report["top"]) == 3 and all(row["solve_rate"] > 0 for row in report["top"])
    assert len(list(top.glob("*.png"))) == 3
    assert main(["curriculum", "inspect", "--run", str(tmp_path / "straight"), "--checkpoint", "3"]) == 1
    assert "checkpoint 3" in capsys.readouterr().err
