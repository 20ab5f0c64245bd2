"""`actors.lockstep`: two real launches (a learner and one actor each, over real zenoh on loopback) with the same
seed write the same learner metrics, bit for bit, for their first 5 updates; without lockstep they would differ
from the first update (the actor's random stream includes its incarnation, and its rollouts race the weights)."""

from __future__ import annotations

import pytest

from impulse.deploy.cli import main
from tests.support.launch_procs import TINY_BATCH, free_port, metrics, start_launch, stop_launch, tail

pytestmark = pytest.mark.heavy

UPDATES = 5


def test_two_lockstep_launches_with_one_seed_write_identical_metrics(tmp_path, capsys) -> None:
    overrides = ("actors.num_actors=1", "actors.lockstep=true", "seed=3", "checkpoint.every_updates=1000",
                 "eval.attempts=0", f"total_env_steps={UPDATES * 8 * 8}", *TINY_BATCH)
    runs = [tmp_path / "first", tmp_path / "second"]
    launches = [start_launch(run, free_port(), *overrides) for run in runs]
    try:
        for (launch, log_path) in launches:
            assert launch.wait(timeout=400) == 0, tail(log_path)
    finally:
        for (launch, _), run in zip(launches, runs):
            stop_launch(launch, run)
    first = metrics(runs[0])
    assert [row["update"] for row in first] == list(range(1, UPDATES + 1)), tail(launches[0][1])
    assert main(["compare", *map(str, runs), "--identical", str(UPDATES)]) == 0, capsys.readouterr().out
    assert all(row["policy_lag"] == 0 for row in first)  # every batch rolled out by the weights just before it
    assert len({row["policy_loss"] for row in first}) == UPDATES  # the policy moved at every update
