"""metrics.jsonl rows as TensorBoard scalars (`monitor.scalars`), read back with TensorBoard's own reader: each
numeric column one tag at step env_steps and wall time time_s; a resumed run's event file hides the points past
its checkpoint that an earlier process wrote; `impulse tensorboard` writes from a metrics.jsonl exactly what the
live run wrote. W&B offline holds the run's name, config and rows; a W&B project without the W&B client stops
`impulse train`, `impulse learner` and `impulse launch` before anything starts, naming the key and the install
command."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

from impulse.deploy.cli import main
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.monitoring import scalar_sinks_for
from impulse.deploy.runtime.preflight import PreflightError, run_preflight
from impulse.deploy.runtime.progress import MetricsFile
from impulse.monitor.scalars import TENSORBOARD_DIR, TensorBoardSink, event_files
from tests.support.launch_procs import free_port
from tests.support.scalars import expected_points, metrics_rows, tensorboard_points, wandb_run


def _row(update: int, value: float) -> dict:
    return {"update": update, "env_steps": 1024 * update, "time_s": 1_800_000_000.5 + update,
            "solve_rate": value, "episode_return": np.float32(value * 2), "eval/mean": math.nan,
            "drops/lost": 3, "note": "text", "eval/kinetix:s": value / 2}


def test_a_resumed_run_hides_the_points_it_redoes(tmp_path: Path) -> None:
    log_dir = tmp_path / TENSORBOARD_DIR
    first = TensorBoardSink(log_dir, resume_env_steps=0)
    for update in (1, 2, 3, 4):
        first.write(_row(update, 0.1 * update))
    first.close()  # killed after update 4; its checkpoint was update 1
    resumed = TensorBoardSink(log_dir, resume_env_steps=1024)
    for update in (2, 3):  # then stopped again, at update 3: what the earlier process wrote at 4 is superseded too
        resumed.write(_row(update, 0.5 + 0.1 * update))
    resumed.close()

    files = event_files(log_dir)
    assert len(files) == 2
    marks = [event.step for event in EventFileLoader(str(files[1])).Load() if event.HasField("session_log")]
    assert marks == [1025], "the resumed file starts by hiding every earlier point past the checkpoint's step"
    points, wall = tensorboard_points(log_dir)
    assert set(points) == {"update", "solve_rate", "episode_return", "drops/lost", "eval/kinetix_s"}, \
        "NaN, text, step and time: no tag; a character TensorBoard refuses becomes _"
    assert points["solve_rate"] == {1024: pytest.approx(0.1), 2048: pytest.approx(0.7), 3072: pytest.approx(0.8)}
    assert points["update"] == {1024: 1, 2048: 2, 3072: 3}
    assert points["episode_return"][3072] == pytest.approx(1.6)
    assert wall == {1024 * u: pytest.approx(1_800_000_000.5 + u) for u in (1, 2, 3)}


def test_export_writes_what_the_live_run_wrote(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    live, copy = tmp_path / "live", tmp_path / "copy"
    metrics = MetricsFile(live / "metrics.jsonl")
    sink = TensorBoardSink(live / TENSORBOARD_DIR, resume_env_steps=0)
    for update in range(1, 6):
        row = _row(update, 1 / (update + 2))
        metrics.write(row)
        sink.write(row)
    metrics.close()
    sink.close()
    copy.mkdir()
    (copy / "metrics.jsonl").write_text((live / "metrics.jsonl").read_text())

    assert main(["tensorboard", str(copy)]) == 0
    assert f"{copy / TENSORBOARD_DIR}: 5 rows" in capsys.readouterr().out
    exported = tensorboard_points(copy / TENSORBOARD_DIR)
    assert exported == tensorboard_points(live / TENSORBOARD_DIR)
    assert exported[0] == expected_points(metrics_rows(copy / "metrics.jsonl"))
    assert len(exported[0]["solve_rate"]) == 5

    # A second export would draw every point twice: refused unless --replace, which rewrites the folder.
    assert main(["tensorboard", str(copy)]) == 2
    assert "--replace" in capsys.readouterr().err
    assert main(["tensorboard", "--replace", str(copy)]) == 0
    assert len(event_files(copy / TENSORBOARD_DIR)) == 1
    assert tensorboard_points(copy / TENSORBOARD_DIR) == exported
    assert main(["tensorboard", str(tmp_path / "nowhere")]) == 2
    assert "no metrics.jsonl" in capsys.readouterr().err


def test_a_sink_without_its_client_stops_before_the_run(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "wandb", None)  # what `import wandb` meets where it is not installed
    for command in ("train", "learner"):
        run_dir = tmp_path / command
        assert main([command, f"run_dir={run_dir}", "monitor.wandb_project=impulse"]) == 2
        err = capsys.readouterr().err
        assert "monitor.wandb_project" in err and "pip install 'impulse[wandb]'" in err, err
        assert not (run_dir / "metrics.jsonl").exists()
    config = resolve_config(RunConfig, overrides=["monitor.wandb_project=impulse", "env.levels=handmade",
                                                  f"bus.hub=tcp/127.0.0.1:{free_port()}"])
    with pytest.raises(PreflightError, match=r"monitor\.wandb_project.*impulse\[wandb\]"):
        run_preflight(config, tmp_path / "launch", resume=False, curriculum_service=False)
    # The same for TensorBoard's writer, on by default: a lent GPU's Python lacked it, and a run failed only after
    # its first compile.
    monkeypatch.setitem(sys.modules, "tensorboardX", None)
    run_dir = tmp_path / "without-tensorboard"
    assert main(["train", f"run_dir={run_dir}"]) == 2
    err = capsys.readouterr().err
    assert "monitor.tensorboard=false" in err and "tensorboardX" in err, err
    assert not (run_dir / "metrics.jsonl").exists()


def test_wandb_offline_holds_the_runs_name_config_and_every_row(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # The sinks a run opens (`scalar_sinks_for`), W&B offline: it writes its run file and contacts no server.
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "wandb-home"))
    monkeypatch.setenv("WANDB_SILENT", "true")
    config = resolve_config(RunConfig, overrides=["name=quick-cpu", "ppo.num_envs=32", "monitor.tensorboard=false",
                                                  "monitor.wandb_project=impulse-tests"])
    [sink] = scalar_sinks_for(config, tmp_path)(0)
    rows = [{**_row(update, 0.1 * update), "episode_return": 0.2 * update} for update in (1, 2, 3)]
    for row in rows:
        sink.write(row)
    sink.close()
    run, logged = wandb_run(tmp_path / "wandb")
    assert run.display_name == run.run_group == "quick-cpu" and run.project == "impulse-tests"
    logged_config = {item.key: json.loads(item.value_json) for item in run.config.update}
    assert logged_config["ppo"]["num_envs"] == 32 and logged_config["name"] == "quick-cpu", logged_config
    assert logged == expected_points(rows, precision=float, tags=False)
