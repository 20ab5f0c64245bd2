"""The default viewer layout for a run: rollouts on the left, training curves in the middle, the curriculum on
the right. Every process sends it with its recording; the viewer uses it until the user arranges their own (a
layout the user changed is kept; "reset blueprint" in the viewer brings this one back)."""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb

from impulse.engine.arena import ARENA_METRES
from impulse.monitor.metrics import CURRICULUM, METRICS
from impulse.monitor.rollouts import env_entity

ARENA_BOUNDS = rrb.VisualBounds2D(x_range=[0.0, ARENA_METRES], y_range=[0.0, ARENA_METRES])
LEARNER_CURVES = {
    "loss": ("total_loss", "value_loss"),
    "policy": ("policy_loss", "entropy", "approx_kl", "clip_fraction"),
    "episodes": ("window/solve_rate", "window/episode_return"),
    "lag and queue": ("policy_lag", "queue"),
    "off-policy": ("behaviour_kl", "trace_weight"),
}
DROPS = ("dropped_stale", "dropped_overflow", "dropped_old_epoch", "lost")
CURRICULUM_CURVES = {
    "buffer scores": ("score_q10", "score_q50", "score_q90", "score_replay_weighted"),
    "buffer solve rates": ("solve_rate_mean", "learnable", "never_solved", "always_solved"),
    "buffer turnover": ("buffer_fill", "count_inserted", "count_evicted", "count_rejected"),
}


def _curves(name: str, path: str, fields: Sequence[str]) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(name=name, origin=path, contents=[f"$origin/{f}" for f in fields])


def side_panels(timeline: str) -> tuple[rrb.BlueprintPanel, rrb.SelectionPanel, rrb.TimePanel]:
    """Room for the views: the blueprint and selection panels folded away (one click brings them back), the time
    panel as its one line of controls on `timeline`."""
    return (rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(timeline=timeline, state="collapsed"))


def scene_view(name: str, path: str) -> rrb.Spatial2DView:
    """A 2D view of one scene entity, framed on the arena."""
    return rrb.Spatial2DView(name=name, origin=path, visual_bounds=ARENA_BOUNDS)


def default_blueprint(actors: Sequence[str], watched: int = 1, gallery: int = 6,
                      curriculum: bool = True) -> rrb.Blueprint:
    """Panels for `actors` (streaming their first `watched` environments), the learner's curves and, when the
    run has a curriculum service, its histograms, statistics and a gallery of its `gallery` top levels."""
    scenes = [scene_view(f"{actor} · env {w}", f"{env_entity(actor, f'env-{w}')}/scene")
              for actor in actors for w in range(max(watched, 0))]
    rollouts = rrb.Vertical(
        rrb.Grid(*scenes, name="live rollouts") if scenes else rrb.TextDocumentView(name="no rollouts streamed"),
        rrb.TimeSeriesView(name="rewards", origin="rollouts"),
        rrb.TextLogView(name="episodes", origin="rollouts"),
        row_shares=[5, 2, 2], name="rollouts")
    learner = f"{METRICS}/learner"
    curves = rrb.Vertical(
        *[_curves(name, learner, fields) for name, fields in LEARNER_CURVES.items()],
        rrb.TimeSeriesView(name="env steps/s", origin=METRICS, contents=[
            "$origin/learner/status/consumed_steps_per_s", *[f"$origin/{a}/status/steps_per_s" for a in actors]]),
        rrb.TimeSeriesView(name="drops", origin=METRICS, contents=[
            *[f"$origin/learner/status/{d}" for d in DROPS],
            *[f"$origin/{a}/status/{c}" for a in actors for c in ("dropped_no_credit", "monitor/rollouts_dropped")]]),
        name="training")
    columns: list[rrb.Container] = [rollouts, curves]
    if curriculum:
        stats = f"{CURRICULUM}/stats"
        columns.append(rrb.Vertical(
            rrb.Horizontal(rrb.BarChartView(name="score histogram", origin=f"{CURRICULUM}/histograms/score"),
                           rrb.BarChartView(name="solve-rate histogram",
                                            origin=f"{CURRICULUM}/histograms/solve_rate")),
            *[_curves(name, stats, fields) for name, fields in CURRICULUM_CURVES.items()],
            rrb.Grid(*[scene_view(f"top {rank + 1}", f"{CURRICULUM}/top/{rank}/scene") for rank in range(gallery)],
                     name="top levels"),
            rrb.Horizontal(rrb.TimeSeriesView(name="knobs", origin=f"{CURRICULUM}/knobs"),
                           rrb.TextLogView(name="knob changes", origin=f"{CURRICULUM}/knob_changes")),
            row_shares=[1, 1, 1, 1, 2, 1], name="curriculum"))
    return rrb.Blueprint(rrb.Horizontal(*columns, column_shares=[3, 2, 2][: len(columns)]), *side_panels("wall"))


def episodes_blueprint(source: str, names: Sequence[str]) -> rrb.Blueprint:
    """A grid of recorded episodes (`impulse eval --record`), one view per level, scrubbed by `episode_step`."""
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Grid(*[scene_view(name, f"{env_entity(source, name)}/scene") for name in names], name="episodes"),
            rrb.Horizontal(rrb.TimeSeriesView(name="rewards", origin=f"rollouts/{source}"),
                           rrb.TextLogView(name="outcomes", origin=f"rollouts/{source}")),
            row_shares=[4, 1]),
        *side_panels("episode_step"))
