"""Batch-scored SFL (`curriculum.sfl_scoring=batch`, Kinetix's form) inside the fused trainer: the buffer is filled
from scored candidates before the first update and again every `sfl_refresh_updates` updates, with the policy
of that moment, and half of every batch is replayed from the first update on. Small sizes: the test checks the
wiring; whether it learns better is a benchmark (benchmarks/RESULTS.md)."""

from __future__ import annotations

import jax
import numpy as np

from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.learner.run import build

CANDIDATES = 16
OVERRIDES = [
    "env.levels=random", "curriculum=sfl", "curriculum.sfl_scoring=batch", f"curriculum.sfl_candidates={CANDIDATES}",
    "curriculum.sfl_attempts=2", "curriculum.sfl_refresh_updates=2", "curriculum.buffer_size=8",
    "curriculum.noop_filter=false", "ppo.num_envs=8", "ppo.num_steps=8", "ppo.num_minibatches=1",
    "ppo.update_epochs=1", "env.observation=symbolic", "network.kind=flat", "network.width=16", "network.depth=1",
    "total_env_steps=256",
]


def test_the_buffer_is_refilled_by_the_policy_on_schedule_and_replayed_from_the_start():
    config = resolve_config(RunConfig, None, OVERRIDES)
    trainer, _, _, levels = build(config)
    init, iterate = trainer.jitted()
    carry = init(jax.random.PRNGKey(0), levels)
    assert int(carry.curriculum.counters.clock) == 0
    clocks, replayed, held = [], [], []
    for _ in range(4):
        carry, metrics = iterate(carry, levels)
        clocks.append(int(carry.curriculum.counters.clock))
        replayed.append(float(metrics["levels_replay"]))
        held.append(bool(carry.curriculum.buffer.filled.any()))  # as the iteration's sample saw it
        if len(clocks) == 1:
            first_filled = np.asarray(carry.curriculum.buffer.filled).sum()
            assert int(carry.curriculum.counters.inserted + carry.curriculum.counters.rejected) == CANDIDATES
    # refills at policy versions 0 and 2: at the start of the 1st and 3rd iteration
    assert clocks == [1, 1, 2, 2]
    counters = carry.curriculum.counters
    assert int(counters.inserted) + int(counters.rejected) == 2 * CANDIDATES
    buffer = carry.curriculum.buffer
    filled = np.asarray(buffer.filled)
    assert (np.asarray(buffer.score_version)[filled] == 2).all()
    scores = np.asarray(buffer.score)[filled]
    assert ((scores > 0) & (scores <= 0.2505)).all(), "learnability p (1 - p) + 0.001 p of the kept levels"
    # half of each batch comes from the buffer whenever it holds a level: here from the first update
    assert int(first_filled) > 0, "no candidate had a learnability above 0 (choose another seed)"
    assert replayed == [0.5 if any_held else 0.0 for any_held in held] and replayed[0] == 0.5


def test_restarted_environments_play_each_batch_from_its_start():
    """`ppo.restart_envs` (Kinetix's SFL form): every rollout starts every environment afresh on the new batch, so
    no episode outlives a rollout; without it, episodes run on across rollouts."""
    timesteps = {}
    for restart in (True, False):
        config = resolve_config(RunConfig, None, [*OVERRIDES, f"ppo.restart_envs={str(restart).lower()}"])
        trainer, _, _, levels = build(config)
        init, iterate = trainer.jitted()
        carry = init(jax.random.PRNGKey(0), levels)
        seen = []
        for _ in range(3):
            carry, _ = iterate(carry, levels)
            seen.append(np.asarray(carry.envs.env_state.timestep))
        timesteps[restart] = np.stack(seen)
    steps = config.ppo.num_steps
    assert (timesteps[True] <= steps).all()
    assert (timesteps[True] == steps).mean() > 0.5, "most episodes run the whole rollout"
    assert (timesteps[False][-1] > steps).any(), "without restarts some episode carries on into a later rollout"
