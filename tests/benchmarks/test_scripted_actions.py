"""The scripted action pattern fed to both our engine and Jax2D (compat_jax2d): its values must stay fixed,
and the files that run inside the reference virtualenv must not import our project (not installed there)."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from impulse.benchmarks.scripted_actions import engine_actions
from tests.support.paths import REPO

BENCHMARKS = REPO / "benchmarks"


def test_layout_and_dtype() -> None:
    actions = engine_actions(0, 3, 2)
    assert actions.dtype == np.float32
    assert actions.shape == (5,)
    assert engine_actions(7, 0, 0).shape == (0,)


def test_motors_alternate_every_20_steps_staggered_by_joint() -> None:
    assert engine_actions(0, 2, 0).tolist() == [1.0, -1.0]
    assert engine_actions(19, 2, 0).tolist() == [1.0, -1.0]
    assert engine_actions(20, 2, 0).tolist() == [-1.0, 1.0]
    assert engine_actions(45, 3, 0).tolist() == [1.0, -1.0, 1.0]


def test_thrusters_fire_one_period_in_three_staggered_by_thruster() -> None:
    # thruster k fires when (step // 15 + k) % 3 == 0
    assert engine_actions(0, 0, 3).tolist() == [1.0, 0.0, 0.0]
    assert engine_actions(14, 0, 3).tolist() == [1.0, 0.0, 0.0]
    assert engine_actions(15, 0, 3).tolist() == [0.0, 0.0, 1.0]
    assert engine_actions(30, 0, 3).tolist() == [0.0, 1.0, 0.0]
    assert engine_actions(45, 0, 3).tolist() == [1.0, 0.0, 0.0]


def test_joint_values_come_before_thrusters() -> None:
    assert engine_actions(20, 1, 1).tolist() == [-1.0, 0.0]
    assert engine_actions(60, 1, 1).tolist() == [-1.0, 0.0]
    assert engine_actions(90, 1, 1).tolist() == [1.0, 1.0]


def _imported_roots(path: Path) -> set[str]:
    roots = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


def test_reference_side_files_do_not_import_the_project() -> None:
    project = {"engine", "benchmarks", "impulse", "tests", "deploy"}
    assert _imported_roots(BENCHMARKS / "scripted_actions.py") <= {"__future__", "numpy"}
    assert not _imported_roots(BENCHMARKS / "_reference_runner.py") & project
    assert not _imported_roots(BENCHMARKS / "reference_env.py") & (project | {"jax", "numpy"})
