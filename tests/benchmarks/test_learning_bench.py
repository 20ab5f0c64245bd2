"""The bookkeeping of benchmarks/learning.py on synthetic runs and metrics rows: evaluation points, lag and drops,
the per-mode summary and the issue's bar (no training, so it stays fast)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

from impulse.benchmarks.learning import (
    HANDMADE,
    KINETIX_S,
    Settings,
    command,
    curve,
    run_health,
    stop_at_timeout,
    summarise,
    update_steps,
)


def run(mode: str, seed: int, final: float, curve_points: list[tuple[float, float]]) -> dict:
    return {"mode": mode, "seed": seed, "wall_s": 100.0, "policy_lag_mean": 1.5 if mode == "distributed" else None,
            "batches_dropped": 1 if mode == "distributed" else 0,
            "final": {KINETIX_S: final, HANDMADE: 0.1},
            "curve": [{"env_steps": 4096, "time_s": t, KINETIX_S: rate, HANDMADE: 0.0} for t, rate in curve_points]}


def test_curve_and_health_read_the_learners_rows() -> None:
    rows = [{"update": 1, "env_steps": 4096, "time_s": 10.0, "policy_lag": 0, "entropy": 5.0, "clip_fraction": 0.1,
             "approx_kl": 0.01},
            {"update": 2, "env_steps": 8192, "time_s": 12.0, "policy_lag": 2, "eval/policy_version": 1.0,
             f"eval/{KINETIX_S}": 0.3, f"eval/{HANDMADE}": 0.2, "drops/dropped_stale": 3, "drops/lost": 0,
             "entropy": 3.0, "clip_fraction": 0.3, "approx_kl": 0.03}]
    [point] = curve(rows, 4096)
    assert point == {"env_steps": 4096.0, "time_s": 2.0, KINETIX_S: 0.3, HANDMADE: 0.2}
    health = run_health(rows)
    assert health["policy_lag_mean"] == 1.0 and health["policy_lag_max"] == 2
    assert health["drops"] == {"dropped_stale": 3} and health["batches_dropped"] == 3 and health["updates"] == 2
    assert math.isclose(health["clip_fraction_mean"], 0.2) and math.isclose(health["approx_kl_mean"], 0.02)
    assert health["entropy_start"] == health["entropy_end"] == 4.0  # both windows hold both rows here


def test_the_bar_holds_within_ninety_percent_and_fails_below() -> None:
    close = [run("fused", s, 0.30, [(10.0, 0.1), (20.0, 0.3)]) for s in range(3)]
    close += [run("distributed", s, 0.28, [(15.0, 0.28)]) for s in range(3)]
    summary = {r["record"] + r.get("mode", ""): r for r in summarise(close, ("fused", "distributed"))}
    assert summary["bar"]["holds"] and math.isclose(summary["bar"]["ratio"], 0.28 / 0.30)
    assert math.isclose(summary["summaryfused"]["target_kinetix_s"], 0.9 * 0.28)
    assert summary["summaryfused"]["seconds_to_target"] == [20.0, 20.0, 20.0]
    assert summary["summarydistributed"]["policy_lag_mean"] == 1.5
    assert math.isclose(summary["summaryfused"]["curve_kinetix_s"], 0.2)  # the mean of 0.1 and 0.3
    assert math.isclose(summary["summarydistributed"]["curve_kinetix_s"], 0.28)

    # Far below, with seeds that agree: neither 90% nor within two standard errors.
    far = [run("fused", s, 0.30 + 0.01 * s, []) for s in range(3)]
    far += [run("distributed", s, 0.10 + 0.01 * s, []) for s in range(3)]
    bar = summarise(far, ("fused", "distributed"))[-1]
    assert bar["record"] == "bar" and not bar["holds"], bar

    # Far below in the mean, but the seeds scatter so widely that the two are within two standard errors.
    noisy = [run("fused", s, rate, []) for s, rate in enumerate((0.0, 0.3, 0.9))]
    noisy += [run("distributed", s, rate, []) for s, rate in enumerate((0.0, 0.1, 0.5))]
    bar = summarise(noisy, ("fused", "distributed"))[-1]
    assert bar["ratio"] < 0.9 and bar["holds"], bar


def test_both_modes_get_the_same_task_and_their_own_evaluation() -> None:
    settings = Settings(("fused", "distributed"), (0,), "sfl", 8192, 4, 5, 2, ("ppo.ent_coef=0.02",), 60.0)
    fused = command("fused", 0, Path("/tmp/f"), settings)
    distributed = command("distributed", 0, Path("/tmp/d"), settings)
    assert fused[3] == "train" and distributed[3] == "launch"
    shared = [a for a in fused if a.startswith(("env.", "network.", "ppo.", "curriculum=", "seed=", "total_env"))]
    assert shared and all(a in distributed for a in shared), shared
    assert "eval.every_updates=4" in fused and "evaluator.every_updates=4" in distributed
    assert "actors.num_actors=2" in distributed and "ppo.ent_coef=0.02" in distributed


def test_an_update_is_as_large_as_the_overrides_make_it() -> None:
    """Curves place points at policy version x update size: the CPU preset's 64 x 64, or what a GPU run sets."""
    assert update_steps(()) == 64 * 64
    assert update_steps(("ppo.num_envs=2048",)) == 2048 * 64



def test_a_run_at_its_time_limit_is_interrupted_so_it_can_checkpoint(tmp_path: Path) -> None:
    """Ctrl-C first (a run checkpoints on SIGINT), a kill only when it does not stop within the grace period."""
    marker = tmp_path / "checkpointed"
    obedient = ("import signal, sys, time, pathlib\n"
                "def stop(*_):\n"
                f"    pathlib.Path({str(marker)!r}).write_text('yes'); sys.exit(0)\n"
                "signal.signal(signal.SIGINT, stop)\n"
                "print('ready', flush=True)\n"
                "time.sleep(60)\n")
    process = subprocess.Popen([sys.executable, "-c", obedient], stdout=subprocess.PIPE)
    assert process.stdout is not None and process.stdout.readline() == b"ready\n"
    assert stop_at_timeout(process, timeout_s=0.2, grace_s=30.0) is None
    assert marker.read_text() == "yes" and process.returncode == 0

    stubborn = ("import signal, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                "print('ready', flush=True)\ntime.sleep(60)\n")
    process = subprocess.Popen([sys.executable, "-c", stubborn], stdout=subprocess.PIPE)
    assert process.stdout is not None and process.stdout.readline() == b"ready\n"
    assert stop_at_timeout(process, timeout_s=0.2, grace_s=0.5) is None
    assert process.returncode == -9

    quick = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    assert stop_at_timeout(quick, timeout_s=30.0) == 3
