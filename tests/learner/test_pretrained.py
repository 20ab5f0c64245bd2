"""The shipped general agent (pretrained/general-s) loads and plays on a fresh clone: it says where it came from,
fits the 10 MB it may take, holds only the policy, and `evaluate_run` scores it as `impulse eval --checkpoint
pretrained/general-s` does."""

from __future__ import annotations

import json

from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.learner.run import evaluate_run
from tests.support.paths import REPO

AGENT = REPO / "pretrained" / "general-s"


def test_the_shipped_agent_loads_and_plays() -> None:
    info = json.loads((AGENT / "agent.json").read_text())
    assert info["env_steps"] > 0 and info["commit"], info
    assert sum(f.stat().st_size for f in AGENT.rglob("*") if f.is_file()) <= 10_000_000
    [step] = (AGENT / "checkpoints").iterdir()
    assert not {"envs", "curriculum"} & {p.name for p in step.iterdir()}, "only the policy is shipped"
    config = resolve_config(RunConfig, AGENT / "config.toml")
    table = evaluate_run(config, AGENT, levels="handmade:s_lander", attempts=4)
    assert set(table) == {"s_lander"} and 0.0 <= table["s_lander"]["solve_rate"] <= 1.0, table
