"""`impulse compare`: two small run directories written by hand (a real config.toml from the config writer, a
metrics.jsonl of made-up rows: no training), compared as a table, as JSON and as a plot; and its one-line errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from impulse.deploy.cli import main
from impulse.deploy.config import resolve_config, write_resolved_config
from impulse.deploy.run_config import RunConfig
from impulse.monitor.runs import SHARED_COLUMNS, read_run

STEPS_A, STEPS_B = 4096, 2048


def write_run(run_dir: Path, overrides: list[str], rows: list[dict], tail: str = "") -> Path:
    """A run directory as `impulse train` or `impulse launch` leaves it: config.toml (the project's own writer) and
    metrics.jsonl (one JSON object per update, then `tail`, e.g. a line cut short by a running run)."""
    write_resolved_config(resolve_config(RunConfig, None, overrides), run_dir)
    lines = [json.dumps({**dict.fromkeys(SHARED_COLUMNS, 0.0), **row}) for row in rows]
    (run_dir / "metrics.jsonl").write_text("".join(line + "\n" for line in lines) + tail)
    return run_dir


@pytest.fixture
def runs(tmp_path: Path) -> tuple[Path, Path]:
    """Run a: fused, finished, 5 updates of 4,096 steps, 10 s apart, solve rate NaN (no episode), .2, .6, .9, .8.
    Run b: distributed, half done (4 of 8 updates of 2,048 steps, 5 s apart), solve rate .1 .3 .4 .45, evaluated at
    updates 2 and 4 (eval/mean .25 and .5), its last line still being written."""
    solve_a = [None, 0.2, 0.6, 0.9, 0.8]
    a = write_run(tmp_path / "a", ["name=a", "total_env_steps=20480", "ppo.num_envs=64", "ppo.num_steps=64"],
                  [{"update": u, "env_steps": STEPS_A * u, "time_s": 1000.0 + 10 * u, "solve_rate": solve_a[u - 1],
                    "reward_per_step": 0.01} for u in range(1, 6)])
    solve_b = [0.1, 0.3, 0.4, 0.45]
    eval_b = {2: {"eval/mean": 0.25, "eval/policy_version": 2}, 4: {"eval/mean": 0.5, "eval/policy_version": 4}}
    b = write_run(tmp_path / "b", ["name=b", "total_env_steps=16384", "ppo.num_envs=32", "ppo.num_steps=64",
                                   "ppo.learning_rate=0.001", "actors.num_actors=4"],
                  [{"update": u, "env_steps": STEPS_B * u, "time_s": 2000.0 + 5 * u, "solve_rate": solve_b[u - 1],
                    "queue": 0, "actor": u % 2, **eval_b.get(u, {})} for u in range(1, 5)],
                  tail='{"update": 5, "env_steps": 102')
    return a, b


def compare(capsys, *args: str | Path) -> tuple[int, str, str]:
    status = main(["compare", *map(str, args)])
    out, err = capsys.readouterr()
    return status, out, err


def cells(out: str, label: str) -> list[str]:
    """The table row of the run `label`, split into its cells (columns are two or more spaces apart)."""
    [row] = [line for line in out.splitlines() if line.startswith(label + " ")]
    return re.split(r"\s{2,}", row.strip())


def test_the_table_shows_progress_final_best_and_steps_to_the_threshold(runs, capsys):
    status, out, err = compare(capsys, *runs, "--threshold", "0.5")
    assert status == 0, err
    header = re.split(r"\s{2,}", out.splitlines()[0].strip())
    assert header == ["run", "mode", "done", "updates", "env steps", "wall",
                      "solve_rate final", "best (at env_steps)", ">=0.5 steps", ">=0.5 time",
                      "eval/mean final", "best (at env_steps)", ">=0.5 steps", ">=0.5 time"]
    # a: final .8, best .9 at update 4 (16,384 steps), .5 first reached at update 3 (12,288 steps, 20 s after
    # the first row); never evaluated.
    assert cells(out, "a") == ["a", "fused", "100%", "5", "20.5k", "0:40", "0.8", "0.9 @16.4k", "12.3k", "0:20",
                               "-", "-", "-", "-"]
    # b: solve rate never reaches .5; eval/mean does at update 4 (8,192 steps, 15 s); the cut line is skipped.
    assert cells(out, "b") == ["b", "distributed", "50%", "4", "8,192", "0:15", "0.45", "0.45 @8,192", "-", "-",
                               "0.5", "0.5 @8,192", "8,192", "0:15"]


def test_the_config_differences_are_listed_below_the_table(runs, capsys):
    status, out, _ = compare(capsys, *runs)
    assert status == 0
    below = out.split("config differences:\n", 1)[1]
    diff = {line.split()[0]: line.split()[1:] for line in below.splitlines()[2:]}
    assert diff == {"total_env_steps": ["20480", "16384"], "ppo.num_envs": ["64", "32"],
                    "ppo.learning_rate": ["0.0001", "0.001"], "actors.num_actors": ["2", "4"]}, below


def test_json_holds_the_same_numbers(runs, capsys):
    status, out, _ = compare(capsys, *runs, "--threshold", "0.5", "--metric", "solve_rate", "--by", "update",
                                  "--json")
    assert status == 0
    report = json.loads(out)
    assert report["metrics"] == ["solve_rate"] and report["by"] == "update" and report["threshold"] == 0.5
    a, b = report["runs"]
    assert (a["label"], a["mode"], a["updates"], a["env_steps"], a["wall_s"], a["done"]) == (
        "a", "fused", 5, 20480, 40.0, 1.0)
    assert a["metrics"]["solve_rate"] == {"final": 0.8, "best": 0.9, "best_at": 4.0, "reached_env_steps": 12288,
                                          "reached_s": 20.0, "reached_update": 3, "window_mean": None,
                                          "window_se": None, "window_points": 0}
    assert (b["mode"], b["done"], b["metrics"]["solve_rate"]["reached_env_steps"]) == ("distributed", 0.5, None)
    assert report["config_diff"]["ppo.learning_rate"] == {"a": 0.0001, "b": 0.001}
    assert "name" not in report["config_diff"] and "run_dir" not in report["config_diff"]


def test_window_means_with_their_standard_errors(runs, capsys):
    status, out, err = compare(capsys, *runs, "--metric", "solve_rate", "--by", "update", "--window", "2:4")
    assert status == 0, err
    assert re.split(r"\s{2,}", out.splitlines()[0].strip())[-1] == "mean 2-4"
    # a: .2, .6, .9 (sample s.d. 0.3512 over 3); b: .3, .4, .45 (s.d. 0.07638 over 3).
    assert cells(out, "a")[-1] == "0.5667 ± 0.2028 (n=3)"
    assert cells(out, "b")[-1] == "0.3833 ± 0.0441 (n=3)"
    status, out, _ = compare(capsys, *runs, "--metric", "solve_rate", "--metric", "eval/mean", "--by", "update",
                             "--window", "4:", "--json")
    report = json.loads(out)
    assert report["window"] == [4.0, None]
    a, b = (run["metrics"] for run in report["runs"])
    assert (a["solve_rate"]["window_mean"], a["solve_rate"]["window_points"]) == (pytest.approx(0.85), 2)
    assert a["solve_rate"]["window_se"] == pytest.approx(0.05)
    assert (a["eval/mean"]["window_mean"], a["eval/mean"]["window_points"]) == (None, 0), "never evaluated"
    assert (b["eval/mean"]["window_mean"], b["eval/mean"]["window_se"], b["eval/mean"]["window_points"]) == (
        0.5, None, 1), "one value: a mean without a standard error"


def test_plot_writes_a_png_of_the_curves(runs, capsys, tmp_path):
    png = tmp_path / "curves" / "cmp.png"
    status, _, err = compare(capsys, *runs, "--plot", png, "--by", "time_s", "--json")
    assert status == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert str(png) in err


def test_a_metric_only_some_runs_have_and_a_path_to_a_runs_file(runs, capsys):
    a, b = runs
    status, out, err = compare(capsys, a / "metrics.jsonl", b / "config.toml", "--metric", "actor")
    assert status == 0, err
    assert cells(out, "a")[6:8] == ["-", "-"] and cells(out, "b")[6:8] == ["0", "1 @2,048"]


def test_the_mode_of_a_run_without_mode_columns_comes_from_its_logs(tmp_path):
    run_dir = write_run(tmp_path / "learner-only", ["name=l"], [{"update": 1, "env_steps": 10, "time_s": 1.0}])
    assert read_run(run_dir).mode == "unknown"
    (run_dir / "logs").mkdir()
    assert read_run(run_dir).mode == "distributed"


def one_line_error(capsys, *args: str | Path) -> str:
    status, out, err = compare(capsys, *args)
    assert status == 2 and out == "" and len(err.strip().splitlines()) == 1, (status, out, err)
    return err.strip()


def test_clear_errors(runs, tmp_path, capsys):
    a, _ = runs
    assert "is not a directory" in one_line_error(capsys, a, tmp_path / "nowhere")
    (tmp_path / "plain").mkdir()
    assert "is not a run directory: it has no config.toml" in one_line_error(capsys, tmp_path / "plain")
    fresh = tmp_path / "fresh"
    write_resolved_config(resolve_config(RunConfig, None, ["name=fresh"]), fresh)
    assert "has no metrics yet" in one_line_error(capsys, a, fresh)
    (fresh / "metrics.jsonl").write_text('{"update": 1, "env_st')  # only a line being written
    assert "has no metrics yet" in one_line_error(capsys, fresh)
    error = one_line_error(capsys, *runs, "--metric", "solve_rat")
    assert "no run has the column 'solve_rat' (did you mean solve_rate" in error
    assert "eval/mean" in error and "queue" in error and "reward_per_step" in error, error
    assert "--by must be one of env_steps, time_s, update, got 'steps'" in one_line_error(capsys, *runs, "--by",
                                                                                          "steps")
    assert "--window must be LOW:HIGH" in one_line_error(capsys, *runs, "--window", "500")
    assert "--window must be LOW:HIGH with numbers, got 'a:b'" in one_line_error(capsys, *runs, "--window", "a:b")
    assert "--window '5:1' is empty" in one_line_error(capsys, *runs, "--window", "5:1")


def test_identical_lists_every_value_that_differs_bit_for_bit(tmp_path, capsys):
    """--identical: runs that agree in every shared column but the machine's (time_s, steps_per_s) pass; a value one
    bit apart, in a column both have, fails with that value named; a column only one run has is not compared."""
    loss = 0.1 + 0.2  # 0.30000000000000004: one bit from 0.3
    rows = [{"update": u, "env_steps": 64 * u, "policy_loss": loss * u, "solve_rate": None} for u in (1, 2, 3)]
    same = write_run(tmp_path / "same", ["name=same"], [{**row, "time_s": 7.0 * row["update"]} for row in rows])
    twin = write_run(tmp_path / "twin", ["name=twin"], [{**row, "steps_per_s": 9.0, "extra": 1} for row in rows])
    off = write_run(tmp_path / "off", ["name=off"], [*rows[:2], {**rows[2], "policy_loss": 0.9}])
    status, out, err = compare(capsys, same, twin, "--identical", "3")
    assert (status, err) == (0, "")
    assert out.startswith("identical: the first 3 updates of same, twin agree bit for bit")
    status, out, _ = compare(capsys, same, off, "--identical", "2")
    assert status == 0
    status, out, _ = compare(capsys, same, off, "--identical", "3")
    assert status == 1
    assert re.split(r"\s{2,}", out.splitlines()[-1].strip()) == ["3", "policy_loss", repr(loss * 3), "0.9"]
    assert compare(capsys, same, write_run(tmp_path / "near", ["name=near"], [
        {**row, "policy_loss": row["policy_loss"] + 1e-16} if row["update"] == 1 else row for row in rows]),
        "--identical", "1")[0] == 1
    status, _, err = compare(capsys, same, off, "--identical", "4")
    assert status == 2 and "fewer than the 4 to check" in err
