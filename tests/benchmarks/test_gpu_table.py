"""benchmarks/gpu_table.py turns a bench-gpu run's JSON lines into the RESULTS table."""

from __future__ import annotations

import json

from impulse.benchmarks.gpu_table import figures, markdown, runs

DEVICE = {"jax_version": "0.11.2", "backend": "gpu", "device": "NVIDIA H100 80GB HBM3"}
RUN = [
    {"bench_gpu": "start", "utc": "2026-12-01T10:00:00Z", "commit": "abc1234"},
    {"system": "impulse", "solver": "phased", "size": "s", "num_envs": 1, "steps_per_s": 50.0, **DEVICE},
    {"system": "impulse", "solver": "phased", "size": "s", "num_envs": 32768, "steps_per_s": 4.0e7, **DEVICE},
    {"system": "impulse", "solver": "phased", "physics_backend": "pallas", "size": "s", "num_envs": 32768,
     "steps_per_s": 1.6e8, **DEVICE},
    {"system": "jax2d", "level": "s/h4_thrust_aim", "num_envs": 32768, "steps_per_s": 4.0e6, "size": "s", **DEVICE},
    {"comparison": "impulse/jax2d", "size": "s", "num_envs": 32768, "speedup": 10.0, **DEVICE},
    {"system": "impulse-env", "size": "s", "num_envs": 32768, "steps_per_s": 2.0e6, **DEVICE},
    {"system": "kinetix-env", "size": "s", "num_envs": 32768, "steps_per_s": 5.0e5, **DEVICE},
    {"system": "impulse-fused-ppo", "physics_backend": "xla", "size": "s", "env_steps_per_s": 3.0e5, **DEVICE},
    {"system": "impulse-fused-ppo", "physics_backend": "pallas", "size": "s", "env_steps_per_s": 4.5e5, **DEVICE},
    {"measure": "throughput", "system": "impulse-distributed", "actors": 2, "size": "s", "env_steps_per_s": 2.5e5},
]


def test_the_newest_run_becomes_a_table_of_the_largest_batches_with_ratios() -> None:
    older = [{"bench_gpu": "start", "utc": "old"}, {"system": "impulse", "solver": "phased", "size": "s",
                                                     "num_envs": 8, "steps_per_s": 1.0}]
    lines = [json.dumps(r) for r in older + RUN] + ["bench-gpu: progress text is skipped", "{not json"]
    grouped = runs(lines)
    assert len(grouped) == 2
    table = figures(grouped[-1])
    assert table["s"]["engine_xla"] == 4.0e7  # the 32,768-env figure, not the 1-env one
    assert table["s"]["engine_pallas"] == 1.6e8 and table["s"]["engine_jax2d"] == 4.0e6
    assert table["s"]["train_pallas"] == 4.5e5 and table["s"]["distributed_2"] == 2.5e5
    assert table["s"]["distributed_1"] is None and table["m"]["engine_xla"] is None
    text = markdown(grouped[-1])
    assert "commit abc1234" in text and "NVIDIA H100 80GB HBM3" in text and "JAX 0.11.2" in text
    assert "| S | 40.00M | 160.00M | 4.00M | 2.00M | 500.0k | 300.0k | 450.0k | - | 250.0k | - |" in text
    assert "| S | 10.00x | 40.00x | 4.00x | 1.50x | 4.00x |" in text
    assert "| M | - | - | - | - | - |" in text


def test_a_run_split_over_calls_is_one_run() -> None:
    second_call = [{"bench_gpu": "start", "utc": "2026-12-01T10:09:00Z", "commit": "abc1234", "call": 2},
                   {"measure": "throughput", "system": "impulse-distributed", "actors": 1, "size": "s",
                    "env_steps_per_s": 1.5e5}]
    first_call = [{**RUN[0], "call": 1}, *RUN[1:]]
    grouped = runs(json.dumps(r) for r in first_call + second_call)
    assert len(grouped) == 1
    table = figures(grouped[0])
    assert table["s"]["engine_xla"] == 4.0e7 and table["s"]["distributed_1"] == 1.5e5
    assert "Run of 2026-12-01T10:00:00Z (in 2 calls) at commit abc1234" in markdown(grouped[0])
