"""Compatibility with Jax2D 1.0.2: every shared Kinetix level run in our engine and in Jax2D from the same file,
under the same engine actions, compared body by body.

For each level and action mode (``zero``: all motors and thrusters off; ``scripted``: the fixed pattern of
benchmarks/scripted_actions.py) both engines take ``--steps`` single engine steps (no Kinetix frame skip). The
measure is the largest distance between the two engines' positions of one body, over the active dynamic bodies
(active, inverse_mass > 0) of the loaded level, after 30, 60 and 120 steps. Jax2D runs in its own virtualenv
(benchmarks/reference_env.py), all levels of one mode in one process (`_reference_runner.py trajectories`, one
compile per size); our side also compiles once per size.

Prints JSON lines: one per (level, mode, solver), then one summary per (mode, solver) (levels, how many within
``--threshold`` at the last step, the fraction, the levels outside with their differences and what was observed,
and the levels within at the last step that exceeded the threshold earlier, with their peak).

What "observed" means for a level outside the threshold (nothing is inferred beyond this): the first step at
which the difference exceeds 1 mm; the contacts between dynamic bodies that may collide (not joined) in our
engine, the first one and the last start before that step; the colliding pairs touching in our engine at that
step, marking the pair whose impulse Jax2D's padded batches wipe (bug B1 of the Jax2D digest, a documented
deliberate difference); and the label ``chaotic`` when the positions agree within 1 mm until two dynamic bodies
start touching and part by more than 1 mm within 15 steps of that start. Bodies are named by global index:
polygons first (the four static arena polygons are 0-3), then circles.

Our side runs once per ``--solver`` (the ``SolverOptions.schedule``: ``phased``, the default; ``jax2d``,
Jax2D's batch order; ``jax2d_wipe``, that order plus Jax2D's padding bug B1); every record and summary names its
solver, and Jax2D runs once per action mode.

    impulse bench compat_jax2d                                   # all 42 levels, zero and scripted, all solvers
    impulse bench compat_jax2d --levels 's/*' --actions zero
    impulse bench compat_jax2d --levels m/h0_unicycle,h4_cartpole --steps 60 --threshold 0.01
    impulse bench compat_jax2d --solver jax2d --actions scripted
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import glob as globlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.benchmarks._harness import LEVELS_DIR, emit, environment, progress, require_levels
from impulse.benchmarks.scripted_actions import engine_actions
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.physics.options import SCHEDULES as SOLVERS
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.step import step

CHECKPOINTS = (30, 60, 120)
DIVERGENCE_M = 1e-3  # "the engines have parted": 1 mm
CHAOS_WINDOW = 15  # steps (a quarter second) from a dynamic-dynamic contact start to parting, for "chaotic"
ACTION_MODES = ("zero", "scripted")


# --- Comparison logic (pure numpy; unit-tested in tests/benchmarks/test_compat_jax2d.py) ---------------------

def checkpoints(steps: int) -> list[int]:
    """The standard checkpoints that fit in ``steps``, plus ``steps`` itself (the step the verdict uses)."""
    return sorted({c for c in CHECKPOINTS if c <= steps} | {steps})


def dynamic_mask(active: np.ndarray, inverse_mass: np.ndarray) -> np.ndarray:
    return np.asarray(active, bool) & (np.asarray(inverse_mass) > 0)


def max_difference(ours: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step, the largest distance between the two engines' positions over the masked bodies, and which body.

    ``ours`` and ``reference`` are [steps, N, 2]. A step where a masked body is NaN or infinite on either side
    gives NaN (never hidden by a max over the others). With no masked body the difference is 0 and the body -1.
    """
    ours, reference, mask = np.asarray(ours, np.float64), np.asarray(reference, np.float64), np.asarray(mask, bool)
    if ours.shape != reference.shape:
        raise ValueError(f"trajectory shapes differ: ours {ours.shape}, reference {reference.shape}")
    if ours.shape[1] != mask.shape[0]:
        raise ValueError(f"mask has {mask.shape[0]} bodies, trajectories {ours.shape[1]}")
    steps = ours.shape[0]
    if not mask.any():
        return np.zeros(steps), np.full(steps, -1)
    distance = np.linalg.norm(ours - reference, axis=-1)  # [steps, N]
    distance = np.where(mask[None, :], distance, -np.inf)
    nonfinite = ~np.isfinite(distance) & mask[None, :]
    distance = np.where(nonfinite, np.inf, distance)
    worst = np.argmax(distance, axis=1)
    diff = np.take_along_axis(distance, worst[:, None], axis=1)[:, 0]
    return np.where(nonfinite.any(axis=1), np.nan, diff), worst


def first_step_over(diff: np.ndarray, limit: float) -> int | None:
    """1-based step at which ``diff`` (indexed from step 1) first exceeds ``limit`` or is NaN; None if never."""
    over = ~(np.asarray(diff) <= limit)
    return int(np.argmax(over)) + 1 if over.any() else None


def jax2d_b1_pairs(num_polygons: int, num_circles: int, batch: int = 16) -> frozenset[tuple[int, int]]:
    """The pairs (global body indices, smaller first) whose accumulated impulse Jax2D's padded contact batches
    overwrite every iteration (bug B1 of the Jax2D digest, not copied by us): the last pair of each kind (polygon
    pairs, circle-polygon, circle pairs, in Jax2D's pair order) whose pair count is not a multiple of ``batch``."""
    P, C = num_polygons, num_circles
    pairs = set()
    if P >= 2 and (P * (P - 1) // 2) % batch:
        pairs.add((P - 2, P - 1))
    if P >= 1 and C >= 1 and (P * C) % batch:
        pairs.add((P - 1, P + C - 1))
    if C >= 2 and (C * (C - 1) // 2) % batch:
        pairs.add((P + C - 2, P + C - 1))
    return frozenset(pairs)


class ContactLog(NamedTuple):
    """Our engine's contact flags over a run: touching[t, p] after step t + 1 for pair p, which joins bodies
    pair_a[p] and pair_b[p] and may collide unless ``collides[p]`` is false (joined bodies)."""

    touching: np.ndarray  # [steps, num_pairs] bool
    pair_a: np.ndarray  # [num_pairs]
    pair_b: np.ndarray
    collides: np.ndarray  # [num_pairs] bool
    b1_pairs: frozenset[tuple[int, int]] = frozenset()  # see jax2d_b1_pairs


def touching_pairs(log: ContactLog, step: int) -> list[list[int]]:
    """The colliding pairs (global body indices) touching at 1-based ``step``."""
    hits = np.asarray(log.touching[step - 1], bool) & np.asarray(log.collides, bool)
    return [[int(log.pair_a[p]), int(log.pair_b[p])] for p in np.flatnonzero(hits)]


def dynamic_contact_onsets(log: ContactLog, dynamic: np.ndarray) -> list[tuple[int, int, int]]:
    """(1-based step, body a, body b) for every start of a contact between two dynamic bodies that may collide
    (touching at that step, not at the one before; touching at step 1 counts as a start), in step order."""
    touching = np.asarray(log.touching, bool)
    if touching.size == 0:
        return []
    dynamic = np.asarray(dynamic, bool)
    eligible = np.asarray(log.collides, bool) & dynamic[log.pair_a] & dynamic[log.pair_b]
    hits = touching & eligible[None, :]
    before = np.concatenate([np.zeros_like(hits[:1]), hits[:-1]])
    return [(int(t) + 1, int(log.pair_a[p]), int(log.pair_b[p])) for t, p in np.argwhere(hits & ~before)]


def observation(diff: np.ndarray, threshold: float, log: ContactLog | None, dynamic: np.ndarray) -> dict[str, Any]:
    """What the difference curve and our engine's contacts show; ``reason`` (a sentence of those facts) only
    when the last step ends outside ``threshold`` or is non-finite.

    The label "chaotic" is given when the positions agree within 1 mm until two dynamic bodies start touching
    and part by more than 1 mm within CHAOS_WINDOW steps of that start."""
    diff = np.asarray(diff, np.float64)
    parted = first_step_over(diff, DIVERGENCE_M)
    over = first_step_over(diff, threshold)
    onsets = dynamic_contact_onsets(log, dynamic) if log is not None else []
    first = onsets[0] if onsets else None
    last = next((o for o in reversed(onsets) if parted is not None and o[0] <= parted), None)
    touching = None if log is None or parted is None else touching_pairs(log, parted)
    b1 = [] if log is None else [pair for pair in touching or [] if tuple(sorted(pair)) in log.b1_pairs]

    def event(o: tuple[int, int, int] | None) -> dict[str, Any] | None:
        return None if o is None else {"step": o[0], "bodies": [o[1], o[2]]}

    record: dict[str, Any] = {
        "first_step_over_1mm": parted,
        "first_step_over_threshold": over,
        "first_dynamic_contact": event(first),
        "last_dynamic_contact_start_before_1mm": event(last),
        "touching_when_over_1mm": touching,
        "jax2d_b1_pairs_touching": b1,
    }
    final = diff[-1]
    nan = np.isnan(diff)
    if np.isfinite(final) and final <= threshold:
        record["reason"] = None
        return record
    if nan.any():
        record["reason"] = f"non-finite position from step {int(np.argmax(nan)) + 1}"
        return record
    if last is not None and parted - last[0] <= CHAOS_WINDOW:
        text = (f"chaotic: within 1 mm until dynamic bodies {last[1]} and {last[2]} start touching at step "
                f"{last[0]}; over 1 mm from step {parted}")
    else:
        if last is not None:
            context = f"{parted - last[0]} steps after dynamic bodies {last[1]} and {last[2]} started touching"
        elif first is not None:
            context = f"before any contact between dynamic bodies (first: {first[1]} and {first[2]}, step {first[0]})"
        else:
            context = "with no contact between dynamic bodies in the run"
        text = f"over 1 mm from step {parted}, {context}"
    text += f"; touching then: {touching}"
    if b1:
        text += f" ({', '.join(map(str, b1))}: the pair whose impulse Jax2D wipes, digest B1)"
    record["reason"] = f"{text}; over {threshold:g} m from step {over}"
    return record


def compare_level(
    ours: np.ndarray, reference: np.ndarray, dynamic: np.ndarray, steps: int, threshold: float,
    log: ContactLog | None = None,
) -> dict[str, Any]:
    """The per-level record (without level name and mode): differences at the checkpoints, verdict and what
    was observed. ``ours``/``reference`` are [steps, N, 2] positions after steps 1..steps."""
    diff, worst = max_difference(ours, reference, dynamic)
    at = {str(c): _round(diff[c - 1]) for c in checkpoints(steps)}
    final = diff[steps - 1]
    peak = int(np.argmax(np.where(np.isnan(diff), np.inf, diff)))  # NaN counts as the peak
    return {
        "max_diff_m": at,
        "within": bool(np.isfinite(final) and final <= threshold),
        "peak_diff_m": _round(diff[peak]),
        "peak_step": peak + 1,
        "worst_body": int(worst[steps - 1]),
        "dynamic_bodies": int(np.count_nonzero(dynamic)),
        **observation(diff[:steps], threshold, log, dynamic),
    }


def summarise(records: Sequence[dict[str, Any]], steps: int, threshold: float) -> dict[str, Any]:
    within = sum(1 for r in records if r["within"])
    # Within at the last step but over the threshold on the way (the verdict only looks at the last step).
    passed_over = [
        {"level": r["level"], "peak_diff_m": r["peak_diff_m"], "peak_step": r["peak_step"]}
        for r in records if r["within"] and not (r["peak_diff_m"] is not None and r["peak_diff_m"] <= threshold)
    ]
    outside = [
        {"level": r["level"], "max_diff_m": r["max_diff_m"], "reason": r["reason"]}
        for r in records if not r["within"]
    ]
    # Largest final difference first; non-finite (null) ones lead.
    final = str(steps)
    outside.sort(key=lambda r: -np.inf if r["max_diff_m"][final] is None else -r["max_diff_m"][final])
    return {"levels": len(records), "steps": steps, "threshold_m": threshold, "within": within,
            "fraction": within / len(records) if records else None, "outside": outside,
            "within_but_over_during_run": passed_over}


def _round(value: float) -> float | None:
    """Four significant digits for the JSON lines; NaN becomes null (JSON has no NaN)."""
    return float(f"{value:.4g}") if np.isfinite(value) else None


# --- Level selection -----------------------------------------------------------------------------------------

def resolve_levels(spec: str | None, root: Path = LEVELS_DIR) -> list[Path]:
    """Level files for ``--levels``: comma-separated globs or names relative to the levels folder ('s/*',
    'm/h0_unicycle', 'h4_*', 'h4_cartpole.json', an absolute path); a name without a size folder is looked up in
    every size folder; ".json" may be left out. All levels of s, m and l when ``spec`` is empty."""
    if not spec:
        return [path for size in "sml" for path in sorted(root.glob(f"{size}/*.json"))]
    found: list[Path] = []
    for token in filter(None, (t.strip() for t in spec.split(","))):
        patterns = [token] if token.endswith(".json") else [f"{token}.json", token]
        matches: list[Path] = []
        for where in ("", "*/"):
            if where and "/" in token:
                break
            for pattern in patterns:
                hits = globlib.glob(os.path.join(root, where + pattern))
                matches = sorted(Path(h) for h in hits if h.endswith(".json") and os.path.isfile(h))
                if matches:
                    break
            if matches:
                break
        if not matches:
            raise SystemExit(f"--levels: no level file matches {token!r} under {root}")
        found.extend(m for m in matches if m not in found)
    return found


def level_name(path: Path) -> str:
    return f"{path.parent.name}/{path.name}"


# --- Running the engines -------------------------------------------------------------------------------------

def action_sequence(steps: int, num_joints: int, num_thrusters: int, mode: str) -> np.ndarray:
    if mode == "zero":
        return np.zeros((steps, num_joints + num_thrusters), np.float32)
    rows = [engine_actions(i, num_joints, num_thrusters) for i in range(steps)]
    return np.stack(rows).reshape(steps, num_joints + num_thrusters).astype(np.float32)


@functools.partial(jax.jit, static_argnames=("sizes", "options"))
def _rollout(state, params, actions, sizes: SceneSizes, options: SolverOptions):
    """Positions [steps, N, 2] and contact flags [steps, num_pairs] after each step; compiled once per size and
    solver options."""

    def body(s, a):
        s, contacts = step(s, params, a, sizes, options)
        return s, (s.bodies.position, contacts.touching)

    return jax.lax.scan(body, state, actions)[1]


def run_ours(path: Path, steps: int, mode: str, solver: str = "phased") -> dict[str, Any]:
    level = load_kinetix_level(path)
    sizes, options = level.sizes, dataclasses.replace(level.options, schedule=solver)
    actions = action_sequence(steps, sizes.num_joints, sizes.num_thrusters, mode)
    positions, touching = _rollout(level.state, level.params, jnp.asarray(actions), sizes, options)
    tables = pair_tables(sizes)
    bodies = level.state.bodies
    return {
        "positions": np.asarray(positions),
        "touching": np.asarray(touching),
        "pair_a": np.asarray(tables.pair_a),
        "pair_b": np.asarray(tables.pair_b),
        "collides": np.asarray(level.state.pair_collides),
        "dynamic": dynamic_mask(np.asarray(bodies.active), np.asarray(bodies.inverse_mass)),
        "b1_pairs": jax2d_b1_pairs(sizes.num_polygons, sizes.num_circles),
    }


def run_reference_mode(paths: Sequence[Path], steps: int, mode: str) -> dict[str, dict[str, Any]]:
    """Jax2D trajectories of all levels in one reference-venv process; keyed by level name."""
    from impulse.benchmarks.reference_env import run_reference

    args = ["trajectories", "--levels", *map(str, paths), "--steps", str(steps), "--actions", mode]
    records = run_reference(args, timeout=3600)
    return {r["level"]: r for r in records if r.get("kind") == "trajectories"}


def run_mode(
    paths: Sequence[Path], steps: int, mode: str, threshold: float, solvers: Sequence[str] = ("phased",)
) -> list[dict[str, Any]]:
    """Jax2D once, then our engine once per solver; one summary per solver."""
    progress(f"compat_jax2d: {mode} actions, Jax2D on {len(paths)} levels ...")
    reference = run_reference_mode(paths, steps, mode)
    missing = [level_name(p) for p in paths if level_name(p) not in reference]
    if missing:
        raise SystemExit(f"the reference runner returned no trajectory for {', '.join(missing)}")
    summaries = []
    for solver in solvers:
        reference_env = {}
        records = []
        for path in paths:
            name = level_name(path)
            ref = reference[name]
            reference_env = {k: ref[k] for k in ("jax_version", "backend", "device")}
            progress(f"compat_jax2d: {mode} actions, ours ({solver}) on {name} ...")
            ours = run_ours(path, steps, mode, solver)
            ref_positions = np.asarray(ref["positions"], np.float64)
            ref_dynamic = dynamic_mask(ref["initial"]["active"], ref["initial"]["inverse_mass"])
            if ref_positions.shape != ours["positions"].shape or not np.array_equal(ref_dynamic, ours["dynamic"]):
                raise SystemExit(f"{name}: the engines disagree on the scene layout (shapes {ref_positions.shape} "
                                 f"vs {ours['positions'].shape}, dynamic bodies {ref_dynamic} vs {ours['dynamic']})")
            log = ContactLog(ours["touching"], ours["pair_a"], ours["pair_b"], ours["collides"], ours["b1_pairs"])
            record = {"benchmark": "compat_jax2d", "level": name, "actions": mode, "solver": solver, "steps": steps,
                      **compare_level(ours["positions"], ref_positions, ours["dynamic"], steps, threshold, log)}
            emit(record)
            records.append(record)
        summary = {"benchmark": "compat_jax2d", "summary": True, "actions": mode, "solver": solver,
                   **summarise(records, steps, threshold), "ours": environment(), "jax2d": reference_env}
        emit(summary)
        summaries.append(summary)
    return summaries


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench compat_jax2d", description=__doc__.split("\n")[0])
    parser.add_argument("--levels", default=None,
                        help="comma-separated globs or names under the levels folder (default: all of s, m, l)")
    parser.add_argument("--steps", type=int, default=max(CHECKPOINTS), help="engine steps (default 120)")
    parser.add_argument("--threshold", type=float, default=0.05, help="metres (default 0.05)")
    parser.add_argument("--actions", default=",".join(ACTION_MODES), help="comma-separated among zero,scripted")
    parser.add_argument("--solver", default=",".join(SOLVERS),
                        help=f"comma-separated among {','.join(SOLVERS)}: our engine's schedule (default: all)")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error("--steps must be at least 1")
    modes = [m.strip() for m in args.actions.split(",") if m.strip()]
    unknown = [m for m in modes if m not in ACTION_MODES]
    if unknown or not modes:
        parser.error(f"--actions: expected some of {', '.join(ACTION_MODES)}, got {args.actions!r}")
    solvers = [m.strip() for m in args.solver.split(",") if m.strip()]
    if not solvers or any(m not in SOLVERS for m in solvers):
        parser.error(f"--solver: expected some of {', '.join(SOLVERS)}, got {args.solver!r}")
    require_levels()
    paths = resolve_levels(args.levels)
    if not paths:
        raise SystemExit(f"no level files under {LEVELS_DIR}")
    for mode in modes:
        run_mode(paths, args.steps, mode, args.threshold, solvers)


if __name__ == "__main__":
    main()
