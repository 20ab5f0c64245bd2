"""Line charts of benchmark JSON lines as PNG files, drawn with Pillow alone (`monitor.charts`).

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
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from impulse.monitor.charts import PALETTE, RGB, Panel, Series, format_tick, nice_ticks, render

__all__ = ["PALETTE", "RGB", "Panel", "Series", "format_tick", "main", "mean_curves", "nice_ticks", "read_records",
           "render"]
"""The chart drawing lives in `monitor.charts` (so `impulse compare --plot` shares it); its names are re-exported
here for the benchmarks that draw curves."""


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
