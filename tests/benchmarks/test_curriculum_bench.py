"""The Pillow chart helper behind benchmarks/curriculum.py: ticks, seed averaging and a PNG that opens (no JAX
work, so it stays fast)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from PIL import Image

from impulse.benchmarks.plot import Panel, Series, main, mean_curves, nice_ticks, render


def test_nice_ticks_cover_the_range_in_round_steps() -> None:
    assert nice_ticks(0.0, 1.0) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    ticks = nice_ticks(0.0, 524_288.0)
    assert ticks == [0, 200_000, 400_000]
    assert nice_ticks(3.0, 3.0)  # a flat range still gets ticks


def test_mean_curves_average_seeds_and_skip_missing_values() -> None:
    records = [
        {"method": "plr", "seed": 0, "env_steps": 0, "rate": 0.2},
        {"method": "plr", "seed": 1, "env_steps": 0, "rate": 0.4},
        {"method": "plr", "seed": 0, "env_steps": 10, "rate": None},
        {"method": "dr", "seed": 0, "env_steps": 0, "rate": 0.1},
    ]
    curves = mean_curves(records, "env_steps", "rate", "method")
    xs, ys = curves["plr"]
    assert xs == [0.0, 10.0] and math.isclose(ys[0], 0.3) and math.isnan(ys[1])
    assert curves["dr"] == ([0.0], [0.1])


def test_render_writes_a_png_with_one_panel_width_each(tmp_path: Path) -> None:
    panels = [
        Panel("a", [Series("DR", [0, 1, 2], [0.1, 0.3, 0.2], (31, 119, 180)),
                    Series("SFL", [0, 1, 2], [0.1, math.nan, 0.4], (214, 39, 40), dashed=True)]),
        Panel("b", [], note="skipped: no levels"),
    ]
    path = render(panels, tmp_path / "out" / "chart.png", title="t")
    with Image.open(path) as image:
        assert image.format == "PNG" and image.width == 2 * 460 and image.height > 340


def test_main_plots_json_lines(tmp_path: Path) -> None:
    lines = tmp_path / "r.jsonl"
    lines.write_text('{"record": "eval", "method": "dr", "x": 0, "y": 0.5}\nnot json\n'
                     '{"record": "config", "method": "dr"}\n{"record": "eval", "method": "dr", "x": 1, "y": 0.7}\n')
    assert main([str(lines), "--where", "record=eval", "--x", "x", "--y", "y", "--group", "method",
                 "--out", str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").stat().st_size > 0


def test_main_fails_clearly_when_a_field_is_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = tmp_path / "r.jsonl"
    lines.write_text('{"method": "dr", "x": 0, "y": 0.5}\n{"method": "dr", "x": 1, "y": 0.7}\n')
    with pytest.raises(SystemExit) as exited:
        main([str(lines), "--x", "x", "--y", "y", "--group", "name", "--out", str(tmp_path / "p.png")])
    assert exited.value.code == 2 and not (tmp_path / "p.png").exists()
    assert "no record has the field(s) name; the records have: method, x, y" in capsys.readouterr().err
