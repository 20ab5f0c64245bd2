"""The bookkeeping of benchmarks/finetune.py on synthetic runs: the summary per level and start, and `--from`,
which summarises earlier outputs without training (no training here, so it stays fast)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from impulse.benchmarks.finetune import main, summarise


def run(start: str, seed: int, rates: list[float], level: str = "handmade:s_hop_over") -> dict:
    curve = [{"env_steps": 1000.0 * (i + 1), "solve_rate": rate} for i, rate in enumerate(rates)]
    return {"record": "run", "start": start, "level": level, "seed": seed, "returncode": 0, "wall_s": 1.0,
            "curve": curve, "final": rates[-1]}


def test_the_summary_gives_final_curve_mean_and_steps_to_solved() -> None:
    runs = [run("pretrained", 0, [0.0, 0.95, 1.0]), run("scratch", 0, [0.0, 0.0, 0.5]),
            run("pretrained", 1, [0.5, 1.0, 1.0]), run("scratch", 1, [0.0, 0.3, 0.9])]
    pretrained, scratch = summarise(runs)
    assert (pretrained["start"], scratch["start"]) == ("pretrained", "scratch")
    assert pretrained["seeds"] == [0, 1] and pretrained["finals"] == [1.0, 1.0]
    assert pretrained["final_mean"] == 1.0 and pretrained["final_se"] == 0.0
    assert math.isclose(pretrained["curve_mean"], (1.95 / 3 + 2.5 / 3) / 2)
    assert pretrained["env_steps_to_solved"] == [2000.0, 2000.0]
    assert scratch["env_steps_to_solved"] == [None, 3000.0]  # 0.5 never reaches 0.9; 0.9 does
    assert math.isclose(scratch["final_mean"], 0.7) and math.isclose(scratch["final_se"], 0.2)


def test_from_summarises_earlier_outputs_together(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    first, later = tmp_path / "first.jsonl", tmp_path / "later.jsonl"
    first.write_text(json.dumps({"record": "config"}) + "\n" + json.dumps(run("pretrained", 0, [1.0])) + "\n")
    later.write_text(json.dumps(run("pretrained", 1, [0.0])) + "\n\n")
    assert main(["--from", str(first), str(later), "--plot", str(tmp_path / "curves.png")]) == 0
    [summary] = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert summary["seeds"] == [0, 1] and summary["final_mean"] == 0.5
    assert (tmp_path / "curves.png").stat().st_size > 0

    broken = tmp_path / "broken.jsonl"
    broken.write_text("{not json\n")
    with pytest.raises(SystemExit, match="broken.jsonl:1: not a JSON line"):
        main(["--from", str(broken)])
    no_runs = tmp_path / "no-runs.jsonl"
    no_runs.write_text(json.dumps({"record": "config"}) + "\n")
    with pytest.raises(SystemExit, match="no run lines"):
        main(["--from", str(no_runs)])
