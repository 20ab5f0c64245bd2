"""The viewer-latency benchmark's reading of a recording: every row once, by family, with the wall clock of its log
call; and its summary."""

from __future__ import annotations

import time

import pytest
import rerun as rr

from impulse.benchmarks.viewer_latency import new_rows, summarise


def test_rows_are_read_once_with_their_log_time(tmp_path) -> None:
    path = tmp_path / "run.rrd"
    recording = rr.RecordingStream("impulse", recording_id="latency")
    recording.save(path)
    before = time.time()
    for step in range(3):
        recording.log("metrics/learner/loss", rr.Scalars(float(step)))
        recording.log("rollouts/actor-0/env-0/scene/polygons", rr.Points2D([[0.0, step]]))
    recording.flush()
    after = time.time()
    seen: set[bytes] = set()
    rows = new_rows(path, seen)
    assert sorted(family for family, _ in rows) == ["metrics"] * 3 + ["rollouts"] * 3
    assert all(before - 0.01 <= logged <= after + 0.01 for _, logged in rows)
    recording.log("metrics/learner/loss", rr.Scalars(9.0))
    recording.flush()
    assert [family for family, _ in new_rows(path, seen)] == ["metrics"]  # only the new row


def test_summary_gives_percentiles_and_the_trend() -> None:
    samples = {"metrics": [(100.0 + i, 0.1 * (i + 1)) for i in range(30)]}  # latency grows over the run
    [row] = summarise(samples, started=100.0, ended=130.0)
    assert row["family"] == "metrics" and row["rows"] == 30
    assert row["latency_max_s"] == pytest.approx(3.0)
    assert row["latency_p50_s"] == pytest.approx(1.55, abs=0.01)
    assert row["p50_first_third_s"] < row["p50_last_third_s"]
