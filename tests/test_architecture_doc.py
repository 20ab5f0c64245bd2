"""docs/architecture.md against the tree: every registry its table names is defined where it says, and every file
the "Adding a ..." sections name exists, so the lists of files a new role, message kind or curriculum method
touches cannot go stale unnoticed."""

from __future__ import annotations

import re

from tests.support.paths import REPO

DOC = (REPO / "docs" / "architecture.md").read_text()
PATH = re.compile(r"`((?:[\w.-]+/)+[\w.-]+\.(?:py|sh|md))`")
"""A backticked path of the tree (templates such as `bus/<family>.py` do not match)."""


def sections(prefix: str) -> dict[str, str]:
    parts = re.split(r"^## ", DOC, flags=re.M)
    return {part.split("\n", 1)[0]: part for part in parts if part.startswith(prefix)}


def test_each_registry_is_defined_where_the_table_says():
    rows = re.findall(r"^\| [^|]+ \| `(\w+)` in `([\w/.]+\.py)` \|", DOC, flags=re.M)
    assert {name for name, _ in rows} == {"PROCESS_ROLES", "ROUTES", "METHODS"}, rows
    for name, path in rows:
        source = (REPO / path).read_text()
        assert re.search(rf"^{name}\b[^=\n]*=", source, flags=re.M), f"{name} is not defined in {path}"


def test_every_file_the_adding_sections_name_exists():
    adding = sections("Adding a")
    assert set(adding) == {"Adding a process role", "Adding a message kind", "Adding a curriculum method"}, adding
    for title, text in adding.items():
        named = PATH.findall(text)
        assert named, f"{title} names no file"
        missing = [path for path in named if not (REPO / path).exists()]
        assert not missing, f"{title} names files that do not exist: {missing}"
