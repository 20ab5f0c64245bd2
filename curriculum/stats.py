"""What the curriculum's buffer looks like, for people and for monitoring (host side, numpy).

`buffer_summary` gives the scalar statistics the service publishes and the fused trainer logs: fill, score
distribution, replay-weighted score and staleness, policy lag of the scores, turnover counters, solve-rate
extremes, lineage depth and level complexity; `metric_columns` picks the few that go into every metrics row.
`buffer_table` lists the buffered levels one per row, and `histogram` bins a column for display.
`inspect_report` and `top_levels` are what `impulse curriculum inspect` shows, from a live service or from a
checkpoint (the same report either way).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import numpy as np

from impulse.curriculum.config import LIVE_KNOBS, CurriculumConfig
from impulse.curriculum.priority import replay_distribution
from impulse.curriculum.state import CurriculumState, config_with_knobs
from impulse.engine.levels.level import Level, level_id_values
from impulse.engine.physics.sizes import SceneSizes

SOLVE_RATE_BINS = np.linspace(0.0, 1.0, 11)


def buffer_table(state: CurriculumState, sizes: SceneSizes) -> dict[str, np.ndarray]:
    """One row per filled buffer slot: slot, id, score, solve rate, episodes, age, staleness, replays, replay
    probability, score version, parent id, generation and complexity counts."""
    buffer = state.buffer
    # Only the per-slot scalars and activity flags travel to the host, never the scenes.
    buffer, clock, p_replay, active, joints, thrusters, level_id = jax.device_get((
        buffer._replace(levels=None), state.counters.clock,
        replay_distribution(buffer, state.knobs, state.counters.clock), buffer.levels.state.bodies.active,
        buffer.levels.state.joints.active, buffer.levels.state.thrusters.active, buffer.levels.level_id))
    filled = np.asarray(buffer.filled, bool)
    episodes = np.asarray(buffer.episodes, np.float64)
    solve_rate = np.where(episodes > 0, np.asarray(buffer.solved) / np.maximum(episodes, 1e-9), np.nan)
    table = {
        "slot": np.arange(filled.size),
        "level_id": level_id_values(level_id),
        "score": np.asarray(buffer.score, np.float64),
        "solve_rate": solve_rate,
        "episodes": episodes,
        "age": clock - np.asarray(buffer.inserted_at),
        "staleness": clock - np.asarray(buffer.last_sampled),
        "replays": np.asarray(buffer.replays),
        "p_replay": p_replay,
        "score_version": np.asarray(buffer.score_version),
        "parent_id": level_id_values(buffer.parent_id),
        "generation": np.asarray(buffer.generation),
        "shapes": np.asarray(active, bool).sum(axis=-1) - sizes.num_static_polygons,
        "joints": np.asarray(joints, bool).sum(axis=-1),
        "thrusters": np.asarray(thrusters, bool).sum(axis=-1),
    }
    return {name: column[filled] for name, column in table.items()}


def histogram(values: np.ndarray, bins: np.ndarray | int = 10) -> dict[str, list[float]]:
    """Counts of the finite `values` in `bins` (edges, or a number of equal bins over their range)."""
    finite = np.asarray(values, np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return {"edges": [], "counts": []}
    counts, edges = np.histogram(finite, bins=bins)
    return {"edges": [float(e) for e in edges], "counts": [int(c) for c in counts]}


def buffer_summary(state: CurriculumState, sizes: SceneSizes, policy_version: int | None = None) -> dict[str, Any]:
    """Scalars describing the buffer and the curriculum's counters (plain floats and ints, JSON-ready)."""
    table = buffer_table(state, sizes)
    counters = {f"count_{name}": int(v) for name, v in zip(state.counters._fields, jax.device_get(state.counters),
                                                            strict=True)}
    size = int(np.asarray(state.buffer.filled).size)
    summary: dict[str, Any] = {"buffer_size": size, "buffer_fill": len(table["slot"]) / size, **counters}
    summary["staged"] = int(np.asarray(state.staging.staged).sum())
    if len(table["slot"]) == 0:
        return summary
    score, weight = table["score"], table["p_replay"]
    weight = weight / weight.sum() if weight.sum() > 0 else np.full(weight.size, 1.0 / weight.size)
    solve_rate = table["solve_rate"]
    scored = np.isfinite(solve_rate)
    summary.update({
        "score_mean": float(score.mean()),
        "score_max": float(score.max()),
        **{f"score_q{q}": float(np.quantile(score, q / 100)) for q in (10, 50, 90)},
        "score_replay_weighted": float((weight * score).sum()),
        "staleness_replay_weighted": float((weight * table["staleness"]).sum()),
        "age_mean": float(table["age"].mean()),
        "solve_rate_mean": float(np.nanmean(solve_rate)) if scored.any() else float("nan"),
        "never_solved": float((solve_rate[scored] == 0).mean()) if scored.any() else float("nan"),
        "always_solved": float((solve_rate[scored] == 1).mean()) if scored.any() else float("nan"),
        "learnable": float(((solve_rate[scored] > 0) & (solve_rate[scored] < 1)).mean()) if scored.any()
        else float("nan"),
        "generation_mean": float(table["generation"].mean()),
        "generation_replay_weighted": float((weight * table["generation"]).sum()),
        "shapes_mean": float(table["shapes"].mean()),
        "joints_mean": float(table["joints"].mean()),
        "thrusters_mean": float(table["thrusters"].mean()),
    })
    if policy_version is not None:
        lag = policy_version - table["score_version"]
        summary["score_lag_mean"] = float(lag.mean())
        summary["score_lag_replay_weighted"] = float((weight * lag).sum())
    return summary


METRIC_COLUMNS = ("buffer_fill", "score_mean", "score_replay_weighted", "learnable", "never_solved", "always_solved",
                  "score_lag_mean", "staleness_replay_weighted", "count_inserted", "count_evicted", "staged")
"""The buffer statistics a learner writes to every metrics.jsonl row, as `curriculum_<name>`: the fused trainer from
its own buffer, the distributed learner from the curriculum service's status line, so that both modes' rows
carry the same columns."""


def metric_columns(summary: Mapping[str, Any]) -> dict[str, float]:
    """The `curriculum_<name>` columns of METRIC_COLUMNS from a `buffer_summary` (or a status line that carries one,
    as heard from another process). A statistic that is missing, not a number or not finite (nothing scored yet)
    is left out of the row rather than written as NaN."""
    columns = {}
    for name in METRIC_COLUMNS:
        value = summary.get(name)
        if isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and np.isfinite(value):
            columns[f"curriculum_{name}"] = float(value)
    return columns


def json_scalar(value: Any) -> Any:
    """A numpy scalar as a plain Python one, and a non-finite float as None (JSON has no NaN)."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def live_knob_values(config: CurriculumConfig, state: CurriculumState) -> dict[str, Any]:
    """The live knobs' current values (they are arrays in the state, changed while a service runs)."""
    current = config_with_knobs(config, state.knobs)
    return {name: getattr(current, name) for name in LIVE_KNOBS}


def inspect_report(state: CurriculumState, sizes: SceneSizes, config: CurriculumConfig, policy_version: int,
                   top: int = 10) -> dict[str, Any]:
    """What `impulse curriculum inspect` shows: method, live knobs, statistics, histograms, the `top` levels by
    score and the lineage of mutated ones (JSON-ready)."""
    table = buffer_table(state, sizes)
    order = np.argsort(-table["score"], kind="stable")
    rows = [{name: json_scalar(column[i]) for name, column in table.items()} for i in order]
    mutated = [row for row in rows if row["generation"] > 0]
    return {
        "method": config.method,
        "knobs": live_knob_values(config, state),
        "policy_version": policy_version,
        "summary": buffer_summary(state, sizes, policy_version),
        "histograms": {
            "score": histogram(table["score"]),
            "solve_rate": histogram(table["solve_rate"], SOLVE_RATE_BINS),
            "age": histogram(table["age"]),
            "replays": histogram(table["replays"]),
        },
        "top": rows[:top],
        "lineage": [{"level_id": r["level_id"], "parent_id": r["parent_id"], "generation": r["generation"]}
                    for r in mutated[:top]],
    }


def top_levels(state: CurriculumState, sizes: SceneSizes, top: int) -> Level:
    """The `top` buffered levels by score, best first (as `inspect_report` ranks them), as one batch on the host."""
    table = buffer_table(state, sizes)
    slots = table["slot"][np.argsort(-table["score"], kind="stable")[:top]]
    return jax.device_get(jax.tree.map(lambda x: x[slots], state.buffer.levels))
