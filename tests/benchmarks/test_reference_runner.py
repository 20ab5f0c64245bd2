"""The reference runner (benchmarks/reference_env.py `run_reference`) runs in the caller's working directory, so a
relative level path means the same file to our benchmark and to Jax2D's or Kinetix's side. Site mode
(`IMPULSE_REFERENCE_SITE`, as on a lent GPU machine) with this interpreter and a folder that holds the two package
names; the script is a real subprocess that reports its working directory and reads a file by a relative path."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from impulse.benchmarks.reference_env import ReferenceEnvError, run_reference


def test_a_relative_path_means_the_same_file_to_the_reference(tmp_path: Path, monkeypatch) -> None:
    site = tmp_path / "site"
    for package in ("jax2d", "kinetix"):
        (site / package).mkdir(parents=True)
    monkeypatch.setenv("IMPULSE_REFERENCE_SITE", str(site))
    work = tmp_path / "work"
    (work / "levels").mkdir(parents=True)
    (work / "levels" / "a.json").write_text('{"level": "a"}')
    script = tmp_path / "runner.py"
    script.write_text("import json, os, sys\n"
                      "print(json.dumps({'cwd': os.getcwd(), 'read': json.load(open(sys.argv[1]))}))\n")
    monkeypatch.chdir(work)
    [record] = run_reference(["levels/a.json"], timeout=60, script=script)
    assert record == {"cwd": os.fspath(work), "read": {"level": "a"}}
    with pytest.raises(ReferenceEnvError, match="No such file"):
        run_reference(["levels/missing.json"], timeout=60, script=script)
