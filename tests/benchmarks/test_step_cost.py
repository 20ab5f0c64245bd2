"""benchmarks/step_cost.py's smoke run (`--quick`: level S, 64 scenes) in-process: every stage of the step is
reported once with a cost analysis, HLO counts, times and a floor that make sense together, and the HLO counting
reads what it says it reads."""

from __future__ import annotations

import json

import pytest

from impulse.benchmarks._harness import LEVELS_DIR
from impulse.benchmarks.step_cost import STAGES, hlo_counts, main

HLO = """HloModule m

%fused_computation (param_0: f32[4]) -> f32[4] {
  %param_0 = f32[4]{0} parameter(0)
  ROOT %add.1 = f32[4]{0} add(%param_0, %param_0)
}

%body (t: (s32[], f32[4])) -> (s32[], f32[4]) {
  %t = (s32[], f32[4]{0}) parameter(0)
  %g = f32[4]{0} get-tuple-element(%t), index=1
  %f = f32[4]{0} fusion(%g), kind=kLoop, calls=%fused_computation
  ROOT %r = (s32[], f32[4]{0}) tuple(%i, %f)
}

ENTRY %main.5 (x.1: f32[4]) -> f32[4] {
  %x.1 = f32[4]{0} parameter(0), metadata={op_name="x"}
  %copy.6 = f32[4]{0} copy(%x.1)
  %fusion.2 = f32[4]{0} fusion(%copy.6), kind=kLoop, calls=%fused_computation
  %while.5 = (s32[], f32[4]{0}) while(%tuple), condition=%c, body=%body
  ROOT %out = f32[4]{0} get-tuple-element(%while.5), index=1
}
"""


def test_hlo_counts_reads_fusions_everywhere_and_ops_of_the_entry_only() -> None:
    # Fusions: one in the loop body, one in the entry. Entry ops: copy, fusion, while (parameter and
    # get-tuple-element move no data).
    assert hlo_counts(HLO) == {"fusions": 2, "entry_ops": 3, "while_loops": 1}


@pytest.mark.skipif(not (LEVELS_DIR / "s").is_dir(), reason=f"Kinetix's level files are not at {LEVELS_DIR}")
def test_quick_run_reports_every_stage_with_a_consistent_cost_model(capsys: pytest.CaptureFixture[str]) -> None:
    main(["--quick"])
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert records[0]["record"] == "environment"
    [ceilings] = [r for r in records if r["record"] == "ceilings"]
    assert ceilings["bandwidth_bytes_per_s"] > 0 and ceilings["rate_flops_per_s"] > 0
    stages = {r["stage"]: r for r in records if r["record"] == "stage"}
    assert list(stages) == list(STAGES)
    for name, r in stages.items():
        assert r["size"] == "s" and r["num_envs"] == 64, name
        assert r["flops"] >= 0 and r["bytes_accessed"] > 0, name
        assert r["fusions"] > 0 and r["entry_ops"] > 0, name
        assert r["time_s"] > 0 and r["compile_s"] > 0 and r["floor_s"] > 0 and r["time_over_floor"] > 0, name
        assert r["floor_s"] == pytest.approx(max(r["bytes_accessed"] / ceilings["bandwidth_bytes_per_s"],
                                                 r["flops"] / ceilings["rate_flops_per_s"])), name
    whole = stages["step"]
    assert whole["share"] == 1.0
    assert whole["bytes_accessed"] >= max(r["bytes_accessed"] for name, r in stages.items() if name != "step")
    assert whole["fusions"] >= max(r["fusions"] for name, r in stages.items() if name != "step")
    # The solver loop is there once and its cost analysis is scaled to the level's sweeps.
    assert stages["solve"]["while_loops"] >= 1 and stages["solve"]["loop_scaled"]
    assert stages["solve"]["flops"] > stages["solve"]["xla_flops"]
