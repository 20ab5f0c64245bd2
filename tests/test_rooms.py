"""The import rules between rooms (DESIGN section 1), checked by reading the source: no module is imported.

The rules keep the lower rooms usable alone (the engine without the learner, the curriculum's pure functions
without the processes) and the dependency graph without cycles: the rooms stand in levels (`LEVELS`), and a room
imports only rooms below it. Imports inside functions count too. No module imports another module's private
(`_underscored`) names.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
OURS = {"engine", "actors", "learner", "curriculum", "bus", "monitor", "studio", "deploy", "benchmarks"}
PACKAGE = "impulse"


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _room_name(name: str) -> str:
    """`impulse.engine.env` -> `engine.env`: the rooms are imported under the one import name `impulse`."""
    return name.removeprefix(PACKAGE + ".")


def our_imports(path: Path, root: Path = REPO) -> set[str]:
    """The modules of ours that `path` imports, named from their room (`engine.env`, without `impulse.`); for
    `from a import b` both `a` and `a.b` (b may be a module)."""
    found: set[str] = set()
    package = _module_name(path, root).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package[: len(package) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return {_room_name(name) for name in found if _room_name(name).split(".")[0] in OURS}


def _within(name: str, *prefixes: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _files(*patterns: str) -> list[Path]:
    files = sorted({f for pattern in patterns for f in REPO.glob(pattern)})
    assert files, patterns
    return files


def _violations(files: list[Path], allowed) -> dict[str, list[str]]:
    bad = {}
    for path in files:
        wrong = sorted(name for name in our_imports(path) if not allowed(name))
        if wrong:
            bad[str(path.relative_to(REPO))] = wrong
    return bad


LEVELS = {"engine": 0, "bus": 1, "curriculum": 2, "monitor": 2, "actors": 3, "learner": 4, "studio": 5, "deploy": 6}
"""How high each room stands: a room imports only rooms of a lower level (and itself). The benchmarks stand beside
`deploy` (they may import everything but its commands)."""


def _room(name: str) -> str:
    return name.split(".")[0]


def test_no_room_imports_a_room_above_or_beside_it():
    bad = {}
    for room, level in LEVELS.items():
        for path in _files(f"{room}/**/*.py"):
            wrong = sorted(n for n in our_imports(path) if _room(n) != room
                           and (_room(n) == "benchmarks" or LEVELS[_room(n)] >= level))
            if wrong:
                bad[str(path.relative_to(REPO))] = wrong
    assert bad == {}


def test_benchmarks_do_not_run_deploys_commands():
    assert _violations(_files("benchmarks/**/*.py"), lambda n: not _within(n, "deploy.commands")) == {}


def private_imports(path: Path) -> set[str]:
    """`module.name` for every `from module import _name` in `path` (dunder names are not private)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.add(f"{'.' * node.level}{node.module or ''}.{alias.name}")
    return found


def test_no_module_imports_another_modules_private_names():
    rooms = [f"{room}/**/*.py" for room in sorted(OURS)]
    bad = {str(path.relative_to(REPO)): sorted(found) for path in _files(*rooms) if (found := private_imports(path))}
    assert bad == {}


RULES = {
    "engine imports only engine": (("engine/**/*.py",), lambda n: _within(n, "engine")),
    "engine/levels does not import engine/env": (("engine/levels/**/*.py",), lambda n: not _within(n, "engine.env")),
    "the rollout and the trajectory type import only engine (and each other)": (
        ("actors/rollout.py", "actors/trajectory.py"),
        lambda n: _within(n, "engine", "actors.rollout", "actors.trajectory"),
    ),
    "curriculum imports only engine and bus": (
        ("curriculum/**/*.py",),
        lambda n: _within(n, "engine", "bus", "curriculum"),
    ),
    "bus imports only bus": (("bus/**/*.py",), lambda n: _within(n, "bus")),
    "monitor imports only engine, bus and monitor": (
        ("monitor/**/*.py",),
        lambda n: _within(n, "engine", "bus", "monitor"),
    ),
    "studio imports only engine, bus, curriculum, monitor, learner and studio": (
        ("studio/**/*.py",),
        lambda n: _within(n, "engine", "bus", "curriculum", "monitor", "learner", "studio"),
    ),
    "nothing but deploy, benchmarks and tests imports studio": (
        tuple(f"{room}/**/*.py" for room in sorted(OURS - {"deploy", "studio", "benchmarks"})),
        lambda n: not _within(n, "studio"),
    ),
    "nothing but deploy, benchmarks and tests imports deploy": (
        tuple(f"{room}/**/*.py" for room in sorted(OURS - {"deploy", "benchmarks"})),
        lambda n: not _within(n, "deploy"),
    ),
}


def third_party_imports(path: Path) -> set[str]:
    """Top-level names of what `path` imports from outside the standard library and our rooms."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.add(node.module.split(".")[0])
    return {name for name in found if name not in sys.stdlib_module_names and name not in OURS | {PACKAGE}}


def test_engine_needs_only_jax_and_numpy():
    """Drawing libraries (Pillow, Rerun) belong to monitor: the engine computes geometry, never pictures."""
    extra = {str(f.relative_to(REPO)): sorted(third_party_imports(f) - {"jax", "numpy"})
             for f in _files("engine/**/*.py")}
    assert {name: found for name, found in extra.items() if found} == {}


@pytest.mark.parametrize("rule", list(RULES))
def test_room_imports(rule):
    patterns, allowed = RULES[rule]
    assert _violations(_files(*patterns), allowed) == {}


def test_the_checker_sees_submodules_relative_and_nested_imports(tmp_path):
    sample = tmp_path / "engine" / "levels" / "sample.py"
    sample.parent.mkdir(parents=True)
    sample.write_text("from impulse.engine import env\nfrom ..physics import step\nimport json\n\n"
                      "def f():\n    from impulse.deploy.cli import main\n")
    assert our_imports(sample, tmp_path) == {
        "engine", "engine.env", "engine.physics", "engine.physics.step", "deploy.cli", "deploy.cli.main"
    }


def function_local_imports(path: Path) -> list[int]:
    """The lines of `path`'s import statements that sit inside a function (a `TYPE_CHECKING` block does not)."""
    lines: list[int] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import | ast.ImportFrom) and in_function:
                lines.append(child.lineno)
            visit(child, in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef))

    visit(ast.parse(path.read_text(), str(path)), False)
    return lines


MOST_LOCAL_IMPORTS_IN_DEPLOY = 20
"""Commands load lazily by name (`deploy.commands.Command.run_function`), so a module of deploy/ imports at its top;
what stays inside a function has a reason there (Rerun only once a monitor is opened, an optional package's clear
error)."""


def test_deploy_imports_at_the_top_of_its_modules(tmp_path):
    found = {str(path.relative_to(REPO)): lines for path in sorted((REPO / "deploy").rglob("*.py"))
             if (lines := function_local_imports(path))}
    assert sum(map(len, found.values())) < MOST_LOCAL_IMPORTS_IN_DEPLOY, found
    sample = tmp_path / "sample.py"
    sample.write_text("import os\n\ndef f():\n    import json\n    if True:\n        from a import b\n")
    assert function_local_imports(sample) == [4, 6]
