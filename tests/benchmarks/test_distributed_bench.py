"""The bytes-per-step part of benchmarks/distributed.py at a tiny batch: the frame is what an actor would send, and
its floors are positive and below it (no processes; one tiny jitted rollout)."""

from __future__ import annotations

import pytest

from impulse.benchmarks.distributed import bytes_per_step


@pytest.mark.parametrize("observation", ["entity", "symbolic"])
def test_actual_bytes_are_at_least_the_floors(observation: str) -> None:
    record = bytes_per_step("s", observation, num_envs=2, num_steps=4, repeats=1)
    assert record["frame_bytes"] == record["bytes_per_step"] * 2 * 4
    assert record["bytes_per_step"] >= record["observation_bytes_per_step"] > 0
    assert record["bytes_per_step"] >= record["floor_compact"] > record["floor_resimulate"] > 0
    assert record["ratio_to_compact"] >= 1.0
