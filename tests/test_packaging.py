"""The installed distribution has one import name, `impulse`: the wheel built from this checkout holds the package
`impulse` and nothing else at its top level (no `engine`, `bus`, `deploy`, ... that would collide with a user's own
modules), every package of the rooms is in it, with the hand-made level files, and it imports and runs from the
wheel's files alone."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.support.paths import REPO

pytestmark = pytest.mark.heavy

ROOMS = ("engine", "bus", "curriculum", "monitor", "actors", "learner", "studio", "deploy", "benchmarks")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    leftover = REPO / "build"  # setuptools builds in the source tree; what it leaves there is not ours to keep
    had_leftover = leftover.exists()
    try:
        built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                                "-w", str(out), str(REPO)], capture_output=True, text=True, timeout=300)
    finally:
        if not had_leftover:
            shutil.rmtree(leftover, ignore_errors=True)
    assert built.returncode == 0, built.stderr[-3000:]
    [path] = out.glob("impulse-*.whl")
    return path


def test_the_wheel_holds_impulse_alone_with_every_package(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    top = {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")}
    assert top == {"impulse"}
    expected = {f"impulse/{path.parent.relative_to(REPO).as_posix()}/__init__.py"
                for room in ROOMS for path in (REPO / room).rglob("__init__.py")}
    assert expected - set(names) == set(), "packages missing from pyproject.toml's [tool.setuptools] packages"
    assert "impulse/engine/levels/handmade/s_easy_car_right.json" in names
    assert {f"impulse/studio/static/{name}" for name in ("index.html", "app.js", "style.css")} <= set(names)
    assert "impulse/studio/static/vendor/uPlot.iife.min.js" in names  # the chart library the pages load
    entry = next(name for name in names if name.endswith("entry_points.txt"))
    assert "impulse = impulse.deploy.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()


def test_the_wheel_imports_and_runs_from_its_own_files(wheel: Path, tmp_path: Path) -> None:
    zipfile.ZipFile(wheel).extractall(tmp_path / "site")
    # Without the checkout, which an editable install of this venv puts on sys.path: the wheel's files alone.
    script = ("import os, sys\n"
              "sys.path = [sys.argv[1]] + [p for p in sys.path if os.path.realpath(p or '.') != sys.argv[2]]\n"
              "import importlib.util, impulse, impulse.deploy.cli as cli\n"
              "assert impulse.__file__.startswith(sys.argv[1]), impulse.__file__\n"
              "assert all(importlib.util.find_spec(room) is None for room in sys.argv[3:]), 'a room at top level'\n"
              "raise SystemExit(cli.main(['levels', 'show', sys.argv[1] + "
              "'/impulse/engine/levels/handmade/s_easy_car_right.json']))\n")
    shown = subprocess.run([sys.executable, "-c", script, str(tmp_path / "site"), str(REPO.resolve()), *ROOMS],
                           cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert shown.returncode == 0, shown.stderr[-3000:]
    assert "s_easy_car_right" in shown.stdout or "green" in shown.stdout.lower(), shown.stdout[-2000:]


def test_the_package_is_a_plain_folder_of_links_to_the_rooms() -> None:
    """No import-path tricks: impulse/ holds one link per room, so the checkout imports as it is, installed or not."""
    package = REPO / "impulse"
    for room in ROOMS:
        assert (package / room).is_symlink() and (package / room).resolve() == REPO / room, room
    assert "__path__" not in (package / "__init__.py").read_text()


def test_a_script_beside_a_clone_named_impulse_imports_the_package(tmp_path: Path) -> None:
    """A folder holding the clone under the name `impulse` and a script of one's own: the script's `import impulse`
    gets the package (its public face included), not the clone's top folder as an empty namespace."""
    (tmp_path / "impulse").symlink_to(REPO, target_is_directory=True)
    script = ("import impulse, sys\n"
              "print(impulse.__file__)\n"
              "assert impulse.make_env is not None and impulse.RunConfig is not None\n")
    shown = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert shown.returncode == 0, shown.stderr[-3000:]
    assert Path(shown.stdout.strip()).resolve() == (REPO / "impulse" / "__init__.py").resolve(), shown.stdout
