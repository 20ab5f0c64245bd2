"""Line charts of benchmark JSON lines as PNG files, drawn with Pillow alone.

Matplotlib is not a dependency of this project and the benchmarks must run on a bare accelerator machine, so the
charts are drawn with Pillow (already required for level rendering): panels side by side, shared legend below,
"nice" axis ticks. `benchmarks.curriculum` uses `render` for its solve-rate curves; run as a benchmark it re-plots
any JSON-lines file, one panel per y field and one line per group, averaging records that share a group and an x
(e.g. several seeds):

    impulse bench plot benchmarks/results/curriculum-cpu-2026-11-23.jsonl --where record=eval \\
        --x env_steps --y handmade_solve_rate kinetix_s_solve_rate --group method --out curves.png
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from PIL import Image, ImageDraw, ImageFont

RGB = tuple[int, int, int]

PALETTE: tuple[RGB, ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
    (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
)
"""Ten colours that stay apart for most colour-blind readers (the common "category 10" set)."""

PANEL_W, PANEL_H = 460, 340
MARGIN_L, MARGIN_R, MARGIN_T, MARGIN_B = 62, 18, 34, 52


@dataclass(frozen=True)
class Series:
    """One line: points in data units (NaN y values leave a gap), drawn in `color`."""

    label: str
    xs: Sequence[float]
    ys: Sequence[float]
    color: RGB
    width: int = 3
    dashed: bool = False
    markers: bool = True


@dataclass(frozen=True)
class Panel:
    """One chart: its series share the axes. `y_range` None scales to the data (from 0)."""

    title: str
    series: list[Series] = field(default_factory=list)
    x_label: str = ""
    y_label: str = ""
    y_range: tuple[float, float] | None = None
    note: str = ""
    """Drawn in grey inside the plot area when the panel has no data (e.g. why a level set was skipped)."""


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    # Pillow's bundled font scales only when Pillow was built with FreeType; the bitmap fallback is small but legible.
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, ImportError):
        return ImageFont.load_default()


def nice_ticks(lo: float, hi: float, target: int = 5) -> list[float]:
    """Round tick values covering [lo, hi] (steps of 1, 2 or 5 times a power of ten), about `target` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(target, 1)
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 5, 10) if m * power >= raw)
    first = math.floor(lo / step + 1e-9) * step
    ticks = []
    value = first
    while value <= hi + step * 1e-9:
        if value >= lo - step * 1e-9:
            ticks.append(round(value, 12))
        value += step
    return ticks


def format_tick(value: float) -> str:
    """Short tick labels: 1.5M, 200k, 5k, 0.25."""
    magnitude = abs(value)
    if magnitude >= 1e6:
        return f"{value / 1e6:g}M"
    if magnitude >= 1e3:
        return f"{value / 1e3:g}k"
    return f"{value:g}"


def _extent(values: Iterable[float]) -> tuple[float, float] | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return (min(finite), max(finite)) if finite else None


def _dashed_line(draw: ImageDraw.ImageDraw, points: list[tuple[float, float]], color: RGB, width: int) -> None:
    dash, gap = 8.0, 5.0
    for (x0, y0), (x1, y1) in zip(points, points[1:]):
        length = math.hypot(x1 - x0, y1 - y0)
        t = 0.0
        while t < length:
            end = min(t + dash, length)
            draw.line([(x0 + (x1 - x0) * t / length, y0 + (y1 - y0) * t / length),
                       (x0 + (x1 - x0) * end / length, y0 + (y1 - y0) * end / length)], fill=color, width=width)
            t = end + gap


def _draw_panel(image: Image.Image, panel: Panel, left: int, top: int) -> None:
    draw = ImageDraw.Draw(image)
    font, small = _font(14), _font(12)
    x0, y0 = left + MARGIN_L, top + MARGIN_T
    x1, y1 = left + PANEL_W - MARGIN_R, top + PANEL_H - MARGIN_B
    draw.text(((x0 + x1) / 2, top + 8), panel.title, fill=(0, 0, 0), font=font, anchor="mt")
    x_extent = _extent(x for s in panel.series for x in s.xs) or (0.0, 1.0)
    if panel.y_range is not None:
        y_lo, y_hi = panel.y_range
    else:
        y_extent = _extent(y for s in panel.series for y in s.ys) or (0.0, 1.0)
        y_lo, y_hi = min(0.0, y_extent[0]), max(y_extent[1], y_extent[0] + 1e-6)
    x_ticks, y_ticks = nice_ticks(*x_extent), nice_ticks(y_lo, y_hi)
    x_lo, x_hi = min(x_ticks[0], x_extent[0]), max(x_ticks[-1], x_extent[1])
    y_lo, y_hi = min(y_ticks[0], y_lo), max(y_ticks[-1], y_hi)
    if x_hi <= x_lo:
        x_hi = x_lo + 1.0

    def to_px(x: float, y: float) -> tuple[float, float]:
        return x0 + (x - x_lo) / (x_hi - x_lo) * (x1 - x0), y1 - (y - y_lo) / (y_hi - y_lo) * (y1 - y0)

    for tick in y_ticks:
        _, py = to_px(x_lo, tick)
        draw.line([(x0, py), (x1, py)], fill=(228, 228, 228), width=1)
        draw.text((x0 - 6, py), format_tick(tick), fill=(60, 60, 60), font=small, anchor="rm")
    for tick in x_ticks:
        px, _ = to_px(tick, y_lo)
        draw.line([(px, y0), (px, y1)], fill=(238, 238, 238), width=1)
        draw.text((px, y1 + 6), format_tick(tick), fill=(60, 60, 60), font=small, anchor="mt")
    draw.rectangle([x0, y0, x1, y1], outline=(90, 90, 90), width=1)
    if panel.x_label:
        draw.text(((x0 + x1) / 2, y1 + 26), panel.x_label, fill=(0, 0, 0), font=small, anchor="mt")
    if panel.y_label:
        label = Image.new("RGBA", (int(y1 - y0), 18), (255, 255, 255, 0))
        ImageDraw.Draw(label).text((label.width / 2, 9), panel.y_label, fill=(0, 0, 0, 255), font=small, anchor="mm")
        upright = label.rotate(90, expand=True)
        image.paste(upright, (left + 4, int(y0)), upright)
    if not any(math.isfinite(y) for s in panel.series for y in s.ys if y is not None) and panel.note:
        draw.text(((x0 + x1) / 2, (y0 + y1) / 2), panel.note, fill=(120, 120, 120), font=small, anchor="mm")

    for series in panel.series:
        runs: list[list[tuple[float, float]]] = [[]]
        for x, y in zip(series.xs, series.ys):
            if y is None or not math.isfinite(y):
                runs.append([])
                continue
            runs[-1].append(to_px(x, y))
        for points in runs:
            if len(points) > 1:
                if series.dashed:
                    _dashed_line(draw, points, series.color, series.width)
                else:
                    draw.line(points, fill=series.color, width=series.width, joint="curve")
            if series.markers:
                r = max(3, series.width // 2 + 2)
                for px, py in points:
                    draw.ellipse([px - r, py - r, px + r, py + r], fill=series.color)


def render(panels: Sequence[Panel], path: Path | str, title: str = "") -> Path:
    """Draw `panels` side by side with one legend (every distinct series label) below; write a PNG to `path`."""
    font = _font(15)
    legend: dict[str, Series] = {}
    for panel in panels:
        for series in panel.series:
            legend.setdefault(series.label, series)
    title_h = 30 if title else 0
    width = PANEL_W * max(len(panels), 1)
    column_w = 170
    per_row = max(1, min(len(legend), (width - 40) // column_w)) if legend else 1
    legend_rows = math.ceil(len(legend) / per_row) if legend else 0
    height = title_h + PANEL_H + 12 + 26 * legend_rows
    image = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    if title:
        draw.text((width / 2, 8), title, fill=(0, 0, 0), font=font, anchor="mt")
    for i, panel in enumerate(panels):
        _draw_panel(image, panel, i * PANEL_W, title_h)
    legend_left = (width - per_row * column_w) // 2
    for i, (label, series) in enumerate(legend.items()):
        row, column = divmod(i, per_row)
        lx, ly = legend_left + column * column_w, title_h + PANEL_H + 6 + 26 * row
        sample = [(lx, ly + 9), (lx + 40, ly + 9)]
        if series.dashed:
            _dashed_line(draw, sample, series.color, series.width)
        else:
            draw.line(sample, fill=series.color, width=series.width)
        draw.text((lx + 48, ly + 9), label, fill=(0, 0, 0), font=_font(13), anchor="lm")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, format="PNG")
    return path


def mean_curves(records: Iterable[dict[str, Any]], x: str, y: str, group: str) -> dict[str, tuple[list, list]]:
    """{group value: (xs, mean y at each x)}: records sharing a group and an x (several seeds) are averaged; a
    missing or non-finite y is left out of the mean (NaN when none is left)."""
    points: dict[str, dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
    for record in records:
        if x not in record or group not in record:
            continue
        value = record.get(y)
        bucket = points[str(record[group])][float(record[x])]
        if isinstance(value, int | float) and math.isfinite(value):
            bucket.append(float(value))
    curves = {}
    for name, by_x in points.items():
        xs = sorted(by_x)
        curves[name] = (xs, [sum(by_x[v]) / len(by_x[v]) if by_x[v] else math.nan for v in xs])
    return curves


def read_records(paths: Iterable[Path], where: dict[str, str]) -> list[dict[str, Any]]:
    """JSON objects of the files' lines whose fields equal (as text) every `where` item; other lines are skipped."""
    records = []
    for path in paths:
        for line in Path(path).read_text().splitlines():
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(record, dict) and all(str(record.get(k)) == v for k, v in where.items()):
                records.append(record)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench plot", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="JSON-lines files (benchmark output)")
    parser.add_argument("--x", required=True, help="field for the x axis")
    parser.add_argument("--y", nargs="+", required=True, help="fields to plot, one panel each")
    parser.add_argument("--group", required=True, help="field whose values name the lines")
    parser.add_argument("--where", nargs="*", default=[], metavar="FIELD=VALUE", help="keep only matching records")
    parser.add_argument("--y-range", nargs=2, type=float, metavar=("LO", "HI"))
    parser.add_argument("--title", default="")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args(argv)
    where = dict(item.split("=", 1) for item in args.where)
    records = read_records(args.files, where)
    if not records:
        parser.error("no records matched")
    missing = [field for field in (args.x, args.group, *args.y) if not any(field in r for r in records)]
    if missing:
        present = sorted({field for r in records for field in r})
        parser.error(f"no record has the field(s) {', '.join(missing)}; the records have: {', '.join(present)}")
    groups = sorted({str(r[args.group]) for r in records if args.group in r})
    colors = {name: PALETTE[i % len(PALETTE)] for i, name in enumerate(groups)}
    panels = []
    for y in args.y:
        curves = mean_curves(records, args.x, y, args.group)
        series = [Series(name, *curves[name], color=colors[name]) for name in groups if name in curves]
        if not series:
            parser.error(f"no record has {args.x}, {y} and {args.group} together: nothing to draw for {y}")
        panels.append(Panel(y, series, x_label=args.x, y_range=tuple(args.y_range) if args.y_range else None))
    print(render(panels, args.out, args.title))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
