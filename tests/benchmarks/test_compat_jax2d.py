"""The comparison logic of benchmarks/compat_jax2d.py on synthetic trajectories (no reference venv, no engine)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from impulse.benchmarks.compat_jax2d import (
    ContactLog,
    checkpoints,
    compare_level,
    dynamic_contact_onsets,
    dynamic_mask,
    first_step_over,
    jax2d_b1_pairs,
    main,
    max_difference,
    resolve_levels,
    summarise,
)


def trajectories(steps: int = 120, bodies: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    ours = rng.normal(size=(steps, bodies, 2))
    return ours, ours.copy()


def no_contacts(steps: int = 120) -> ContactLog:
    return ContactLog(np.zeros((steps, 1), bool), np.array([0]), np.array([1]), np.array([True]))


def test_identical_trajectories_differ_by_zero() -> None:
    ours, ref = trajectories()
    diff, _ = max_difference(ours, ref, np.ones(4, bool))
    assert diff.shape == (120,) and np.all(diff == 0)


def test_difference_is_the_largest_distance_over_masked_bodies_only() -> None:
    ours, ref = trajectories(steps=3)
    ref[1, 0] += [3.0, 4.0]  # 5 m on body 0 (masked out: a static body)
    ref[1, 2] += [0.0, 0.2]
    ref[2, 3] += [0.1, 0.0]
    mask = np.array([False, True, True, True])
    diff, worst = max_difference(ours, ref, mask)
    np.testing.assert_allclose(diff, [0.0, 0.2, 0.1], atol=1e-12)
    assert worst[1:].tolist() == [2, 3]


def test_nan_on_a_masked_body_is_not_hidden_but_nan_on_a_static_one_is_ignored() -> None:
    ours, ref = trajectories(steps=2)
    ours[0, 0] = np.nan
    ours[1, 1] = np.nan
    diff, _ = max_difference(ours, ref, np.array([False, True, True, True]))
    assert diff[0] == 0.0 and np.isnan(diff[1])


def test_no_dynamic_body_gives_zero_and_shape_mismatch_raises() -> None:
    ours, ref = trajectories(steps=2)
    diff, worst = max_difference(ours, ref, np.zeros(4, bool))
    assert diff.tolist() == [0.0, 0.0] and worst.tolist() == [-1, -1]
    with pytest.raises(ValueError):
        max_difference(ours, ref[:, :3], np.ones(4, bool))


def test_dynamic_mask_needs_active_and_finite_mass() -> None:
    mask = dynamic_mask(np.array([True, True, False]), np.array([0.0, 2.0, 2.0]))
    assert mask.tolist() == [False, True, False]


def test_checkpoints_and_first_step_over() -> None:
    assert checkpoints(120) == [30, 60, 120]
    assert checkpoints(50) == [30, 50]
    assert checkpoints(200) == [30, 60, 120, 200]
    assert first_step_over(np.array([0.0, 0.002, 0.0]), 1e-3) == 2
    assert first_step_over(np.array([0.0, np.nan]), 1e-3) == 2
    assert first_step_over(np.zeros(5), 1e-3) is None


def test_a_level_within_threshold() -> None:
    ours, ref = trajectories()
    ref[:, 1, 0] += 0.01  # 1 cm throughout
    record = compare_level(ours, ref, np.ones(4, bool), 120, 0.05, no_contacts())
    assert record["within"] is True and record["reason"] is None
    assert record["max_diff_m"] == {"30": 0.01, "60": 0.01, "120": 0.01}
    assert record["first_step_over_1mm"] == 1 and record["first_step_over_threshold"] is None
    assert record["peak_diff_m"] == 0.01
    assert json.loads(json.dumps(record)) == record


def test_growth_after_a_dynamic_collision_is_labelled_chaotic() -> None:
    steps = 120
    ours, ref = trajectories(steps)
    ref[59:, 2, 0] += np.linspace(0.002, 0.3, steps - 59)  # parts at step 60, 30 cm at the end
    touching = np.zeros((steps, 2), bool)
    touching[57:, 0] = True  # dynamic bodies 1 and 2 start touching at step 58
    touching[:, 1] = True  # static 0 with dynamic 1: always, and not a dynamic-dynamic contact
    log = ContactLog(touching, np.array([1, 0]), np.array([2, 1]), np.array([True, True]))
    record = compare_level(ours, ref, np.array([False, True, True, True]), steps, 0.05, log)
    assert record["within"] is False
    assert record["first_step_over_1mm"] == 60
    assert record["first_dynamic_contact"] == {"step": 58, "bodies": [1, 2]}
    assert record["touching_when_over_1mm"] == [[1, 2], [0, 1]]
    assert record["reason"].startswith("chaotic: within 1 mm until dynamic bodies 1 and 2 start touching at step 58")
    assert record["max_diff_m"]["120"] == pytest.approx(0.3, rel=1e-3)
    assert record["peak_step"] == 120


def test_a_level_back_within_at_the_end_reports_its_peak() -> None:
    ours, ref = trajectories(steps=60)
    ref[29, 1, 0] += 0.2  # 20 cm at step 30 only
    record = compare_level(ours, ref, np.ones(4, bool), 60, 0.05, no_contacts(60))
    assert record["within"] is True and record["reason"] is None
    assert (record["peak_diff_m"], record["peak_step"]) == (0.2, 30)
    summary = summarise([{"level": "s/x.json", **record}], 60, 0.05)
    assert summary["within_but_over_during_run"] == [{"level": "s/x.json", "peak_diff_m": 0.2, "peak_step": 30}]


def test_divergence_without_dynamic_contact_is_not_labelled_chaotic() -> None:
    steps = 60
    ours, ref = trajectories(steps)
    ref[9:, 3, 1] += 0.1
    record = compare_level(ours, ref, np.ones(4, bool), steps, 0.05, no_contacts(steps))
    assert record["within"] is False
    assert record["reason"] == (
        "over 1 mm from step 10, with no contact between dynamic bodies in the run; touching then: []; "
        "over 0.05 m from step 10"
    )


def test_joined_pairs_and_long_past_contacts_do_not_count_as_collisions() -> None:
    steps = 100
    touching = np.zeros((steps, 2), bool)
    touching[4:, 0] = True  # bodies 1, 2 joined by a joint: never a collision
    touching[9:, 1] = True  # bodies 2, 3 touch from step 10 on
    log = ContactLog(touching, np.array([1, 2]), np.array([2, 3]), np.array([False, True]))
    assert dynamic_contact_onsets(log, np.ones(4, bool)) == [(10, 2, 3)]
    ours, ref = trajectories(steps)
    ref[69:, 3, 0] += 1.0  # parts at step 70, 60 steps after the contact started
    record = compare_level(ours, ref, np.ones(4, bool), steps, 0.05, log)
    assert not record["reason"].startswith("chaotic")
    assert "60 steps after dynamic bodies 2 and 3 started touching" in record["reason"]


def test_non_finite_level_is_outside() -> None:
    ours, ref = trajectories(steps=30)
    ours[20:, 1] = np.nan
    record = compare_level(ours, ref, np.ones(4, bool), 30, 0.05, no_contacts(30))
    assert record["within"] is False and record["max_diff_m"]["30"] is None
    assert record["reason"] == "non-finite position from step 21"


def test_b1_pairs_match_the_digest_for_kinetix_sizes() -> None:
    assert jax2d_b1_pairs(5, 2) == {(3, 4), (4, 6), (5, 6)}  # S: rr (3,4), cr (c1, p4), cc (c0, c1)
    assert jax2d_b1_pairs(6, 3) == {(4, 5), (5, 8), (7, 8)}
    assert jax2d_b1_pairs(12, 4) == {(10, 11), (14, 15)}  # L: 48 circle-polygon pairs fill 3 batches exactly


def test_b1_pair_touching_is_named_in_the_reason() -> None:
    steps = 20
    ours, ref = trajectories(steps, bodies=6)
    ref[3:, 5] += 0.2
    touching = np.ones((steps, 1), bool)
    log = ContactLog(touching, np.array([4]), np.array([5]), np.array([True]), jax2d_b1_pairs(6, 0))
    record = compare_level(ours, ref, np.array([False] * 5 + [True]), steps, 0.05, log)
    assert record["jax2d_b1_pairs_touching"] == [[4, 5]]
    assert "[4, 5]: the pair whose impulse Jax2D wipes, digest B1" in record["reason"]


def test_summary_counts_and_orders_levels_outside() -> None:
    records = [
        {"level": "s/a.json", "within": True, "max_diff_m": {"120": 0.01}, "peak_diff_m": 0.01, "reason": None},
        {"level": "s/b.json", "within": False, "max_diff_m": {"120": 0.07}, "peak_diff_m": 0.07, "reason": "x"},
        {"level": "m/c.json", "within": False, "max_diff_m": {"120": 0.9}, "peak_diff_m": 0.9, "reason": "y"},
        {"level": "l/d.json", "within": False, "max_diff_m": {"120": None}, "peak_diff_m": None, "reason": "z"},
    ]
    summary = summarise(records, 120, 0.05)
    assert (summary["levels"], summary["within"], summary["fraction"]) == (4, 1, 0.25)
    assert [r["level"] for r in summary["outside"]] == ["l/d.json", "m/c.json", "s/b.json"]
    assert summary["within_but_over_during_run"] == []


def test_resolve_levels_by_name_glob_and_size(tmp_path: Path) -> None:
    for name in ("s/a1.json", "s/b.json", "m/a2.json", "l/c.json"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text("{}")
    names = lambda paths: [f"{p.parent.name}/{p.name}" for p in paths]  # noqa: E731
    assert names(resolve_levels(None, tmp_path)) == ["s/a1.json", "s/b.json", "m/a2.json", "l/c.json"]
    assert names(resolve_levels("s/*", tmp_path)) == ["s/a1.json", "s/b.json"]
    assert names(resolve_levels("a*", tmp_path)) == ["m/a2.json", "s/a1.json"]
    assert names(resolve_levels("c, s/b.json,c", tmp_path)) == ["l/c.json", "s/b.json"]
    with pytest.raises(SystemExit):
        resolve_levels("zzz", tmp_path)


def test_unknown_solver_is_refused_before_any_engine_runs() -> None:
    with pytest.raises(SystemExit) as raised:
        main(["--solver", "phased,gauss"])
    assert raised.value.code == 2  # argparse's usage error, raised before the reference venv or levels are touched
