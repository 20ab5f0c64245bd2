"""Line charts as PNG files, drawn with Pillow alone: panels side by side, one legend below, "nice" axis ticks.

Matplotlib is not a dependency of this project and the charts must be drawn on a bare accelerator machine too, so
they are drawn with Pillow (already required for level rendering). Two kinds of callers share them: the benchmarks
(`benchmarks.plot`, `impulse bench plot`, the learning curves of `benchmarks.curriculum`, `learning` and
`finetune`) and `impulse compare --plot` (`monitor.runs.plot_runs`); the command stands in `deploy`, which may not
import the benchmarks, hence this module in a room both may import.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

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
    label_font = _font(13)
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    longest = max((measure.textlength(label, font=label_font) for label in legend), default=0)
    column_w = max(170, int(longest) + 60)  # a sample line, a gap and the longest label
    per_row = max(1, min(len(legend), (width - 40) // column_w)) if legend else 1
    legend_rows = math.ceil(len(legend) / per_row) if legend else 0
    height = title_h + PANEL_H + 12 + 26 * legend_rows
    image = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    if title:
        draw.text((width / 2, 8), title, fill=(0, 0, 0), font=font, anchor="mt")
    for i, panel in enumerate(panels):
        _draw_panel(image, panel, i * PANEL_W, title_h)
    legend_left = max(0, (width - per_row * column_w) // 2)
    for i, (label, series) in enumerate(legend.items()):
        row, column = divmod(i, per_row)
        lx, ly = legend_left + column * column_w, title_h + PANEL_H + 6 + 26 * row
        sample = [(lx, ly + 9), (lx + 40, ly + 9)]
        if series.dashed:
            _dashed_line(draw, sample, series.color, series.width)
        else:
            draw.line(sample, fill=series.color, width=series.width)
        draw.text((lx + 48, ly + 9), label, fill=(0, 0, 0), font=label_font, anchor="lm")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, format="PNG")
    return path
