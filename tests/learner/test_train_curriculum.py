"""`impulse train curriculum=sfl` end to end on random levels at small sizes: the curriculum's state rides in the
fused carry, its statistics reach metrics.jsonl, it is checkpointed as the `curriculum` item, and a resumed run
continues with the buffer it had."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np

from deploy.cli import main
from deploy.config import resolve_config
from learner.checkpoint import CURRICULUM, Checkpointer
from learner.config import TrainConfig
from learner.run import build

REPO = Path(__file__).resolve().parents[2]
QUICK = REPO / "configs" / "quick-cpu.toml"
UPDATES = 6
SETTINGS = ["env.levels=random", "curriculum=sfl", "curriculum.buffer_size=32", "curriculum.candidate_episodes=2",
            "curriculum.min_fill=0", "curriculum.noop_filter=false", "ppo.num_envs=16", "ppo.num_steps=32",
            "ppo.num_minibatches=2", "ppo.update_epochs=2", "checkpoint.every_updates=3", "eval.attempts=0",
            f"total_env_steps={UPDATES * 16 * 32}"]


def test_train_sfl_checkpoints_and_resumes_its_buffer(tmp_path: Path) -> None:
    run_dir = tmp_path / "sfl"
    assert main(["train", "--config", str(QUICK), f"run_dir={run_dir}", *SETTINGS, "--updates", "3"]) == 0
    config = resolve_config(TrainConfig, run_dir / "config.toml")
    trainer, *_ = build(config)
    template = jax.eval_shape(trainer.init, jax.random.PRNGKey(0), None).curriculum
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        items, _, _ = checkpoints.restore({CURRICULUM: template})
    saved = items[CURRICULUM]
    assert int(saved.counters.results) > 0 and int(saved.counters.new_batches) == 4  # init's batch + 3 updates

    assert main(["train", "--resume", str(run_dir)]) == 0
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in records] == list(range(1, UPDATES + 1))
    inserted = [r["curriculum_count_inserted"] for r in records]
    assert inserted == sorted(inserted) and inserted[-1] >= int(saved.counters.inserted)
    assert all(r["levels_new"] + r["levels_replay"] == 1.0 for r in records)
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        assert checkpoints.latest_step() == UPDATES
        items, _, _ = checkpoints.restore({CURRICULUM: template})
    final = items[CURRICULUM]
    assert int(final.counters.new_batches) == UPDATES + 1, "the resumed run continued the saved curriculum"
    filled = np.asarray(final.buffer.filled)
    solve = np.asarray(final.buffer.solved)[filled] / np.maximum(np.asarray(final.buffer.episodes)[filled], 1e-9)
    assert (solve > 0).all(), "SFL keeps no level its policy never solved"
