"""Draw the house: which room imports which, read from the source (no module is imported), as a Graphviz picture
and a Mermaid block for docs/architecture.md.

    python -m tools.import_graph            # prints the Mermaid block and the edge counts
    python -m tools.import_graph --png docs/architecture-imports.png   # also renders with Graphviz's `dot`

An arrow A -> B means some module of room A imports room B (the label counts the modules that do). The rooms stand
in levels (tests/test_rooms.py `LEVELS`): every arrow must point down the picture.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOMS = ("deploy", "benchmarks", "studio", "learner", "actors", "curriculum", "monitor", "bus", "engine")
"""Top to bottom, as the picture draws them."""


def _room(module: str) -> str:
    """The room a module name belongs to: `impulse.engine.env` -> `engine` (other names: their first part)."""
    parts = module.split(".")
    return parts[1] if parts[0] == "impulse" and len(parts) > 1 else parts[0]


def room_edges(repo: Path = REPO) -> Counter[tuple[str, str]]:
    """(importing room, imported room) -> how many modules of the first import the second."""
    edges: Counter[tuple[str, str]] = Counter()
    for room in ROOMS:
        for path in sorted((repo / room).rglob("*.py")):
            imported: set[str] = set()
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    imported.update(_room(alias.name) for alias in node.names)
                elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                    imported.add(_room(node.module))
            for other in imported & set(ROOMS) - {room}:
                edges[room, other] += 1
    return edges


def mermaid(edges: Counter[tuple[str, str]]) -> str:
    lines = ["```mermaid", "flowchart TD"]
    lines += [f"    {a} -->|{n}| {b}" for (a, b), n in sorted(edges.items(), key=lambda e: (ROOMS.index(e[0][0]),
                                                                                       ROOMS.index(e[0][1])))]
    return "\n".join([*lines, "```"])


def dot(edges: Counter[tuple[str, str]]) -> str:
    lines = ["digraph rooms {", "  rankdir=TB; node [shape=box, style=rounded, fontname=Helvetica];",
             "  edge [color=gray40, fontname=Helvetica, fontsize=10];"]
    lines += [f"  {room};" for room in ROOMS]
    lines += [f'  {a} -> {b} [label="{n}"];' for (a, b), n in sorted(edges.items())]
    return "\n".join([*lines, "}"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--png", type=Path, help="render the graph to this PNG with Graphviz's dot")
    args = parser.parse_args(argv)
    edges = room_edges()
    print(mermaid(edges))
    if args.png:
        subprocess.run(["dot", "-Tpng", "-Gdpi=110", "-o", str(args.png)], input=dot(edges), text=True, check=True)
        print(f"wrote {args.png}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
