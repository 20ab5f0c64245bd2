"""The curriculum columns of a metrics row: the same picker serves the fused trainer (its own buffer) and the
distributed learner (a status line heard from the curriculum service, so anything may be in it)."""

from __future__ import annotations

import math

import numpy as np

from impulse.curriculum.stats import METRIC_COLUMNS, metric_columns


def test_metric_columns_keep_finite_numbers_of_the_named_statistics_only():
    heard = {"buffer_fill": 0.5, "score_mean": np.float32(0.25), "count_inserted": 12, "learnable": None,
             "never_solved": math.nan, "always_solved": True, "staged": "3", "score_max": 0.9,
             "score_lag_mean": math.inf}
    assert metric_columns(heard) == {"curriculum_buffer_fill": 0.5, "curriculum_score_mean": 0.25,
                                     "curriculum_count_inserted": 12.0}
    assert all(type(v) is float for v in metric_columns(heard).values())
    assert "score_max" not in METRIC_COLUMNS and metric_columns({}) == {}
