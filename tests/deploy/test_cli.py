"""The `impulse` command: help, version, --print-config, commands not built yet, and `impulse bench`."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from impulse.deploy.cli import main
from impulse.deploy.commands import COMMANDS, bench, options
from impulse.engine.physics.sizes import SIZE_NAMES
from tests.support.paths import REPO

REPO_ROOT = REPO


def impulse(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the installed console script when there is one (as a user would), else `python -m impulse.deploy.cli`."""
    script = Path(sys.executable).with_name("impulse")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "impulse.deploy.cli"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO_ROOT), os.environ.get("PYTHONPATH")]))}
    return subprocess.run(
        [*command, *args], cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120, check=False
    )


def test_help_lists_every_command() -> None:
    result = impulse("--help")
    assert result.returncode == 0, result.stderr
    for name in ("train", "launch", "learner", "actor", "curriculum", "router", "eval", "levels", "view", "bench"):
        assert name in result.stdout


def test_every_command_names_a_function_that_runs_it_and_the_parser_knows_the_sizes() -> None:
    # The table names each command's function by module and name (the parser loads no command module); a row whose
    # name is misspelt fails here rather than when a user first runs the command.
    for command in COMMANDS:
        assert callable(command.run_function()), command.runs
    assert options.SIZE_NAMES == SIZE_NAMES


def test_print_config_shows_overrides(tmp_path: Path) -> None:
    config_file = tmp_path / "run.toml"
    config_file.write_text("[network]\nwidth = 64\n")
    result = impulse("train", "--config", str(config_file), "ppo.learning_rate=3e-4", "--print-config", "env.size=m")
    assert result.returncode == 0, result.stderr
    printed = tomllib.loads(result.stdout)
    assert printed["ppo"]["learning_rate"] == 3e-4
    assert printed["env"]["size"] == "m"
    assert printed["network"]["width"] == 64
    assert printed["ppo"]["num_envs"] == 2048


def test_router_names_a_missing_credentials_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["router", f"router.credentials={tmp_path / 'nowhere'}"]) == 2
    err = capsys.readouterr().err.strip()
    assert "credentials directory" in err and "nowhere" in err and "\n" not in err


def test_view_needs_a_run_directory_and_a_free_port(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["view", str(tmp_path)]) == 2
    assert "no config.toml" in capsys.readouterr().err
    (tmp_path / "config.toml").write_text("[monitor]\nurl = 'http://localhost:1/'\n")
    assert main(["view", str(tmp_path)]) == 2
    assert "monitor.url must look like rerun+http://HOST:PORT/proxy" in capsys.readouterr().err
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        (tmp_path / "config.toml").write_text(f"[monitor]\nurl = 'rerun+http://127.0.0.1:{port}/proxy'\n")
        assert main(["view", str(tmp_path)]) == 1
        assert "something already listens" in capsys.readouterr().err


def test_curriculum_knob_commands_need_a_run_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["curriculum", "get", "--run", str(tmp_path)]) == 2
    assert "no config.toml" in capsys.readouterr().err


def test_curriculum_commands_against_a_run_without_a_curriculum_fail_at_once(tmp_path: Path, capsys) -> None:
    (tmp_path / "config.toml").write_text("name = 'fixed'\n[env]\nlevels = 'handmade'\n")
    for action in (["get"], ["set", "replay_prob=0.2"], ["inspect"]):
        assert main(["curriculum", *action, "--run", str(tmp_path)]) == 2
        assert "has no curriculum service: it plays the fixed level set" in capsys.readouterr().err


def test_a_curriculum_on_a_fixed_level_set_is_a_usage_error(tmp_path: Path, capsys) -> None:
    assert main(["launch", f"run_dir={tmp_path / 'run'}", "curriculum=plr", "env.levels=handmade"]) == 2
    assert "curriculum.method=plr needs env.levels=random" in capsys.readouterr().err


def test_a_learner_on_several_hosts_needs_its_place_and_a_coordinator(tmp_path: Path, capsys, monkeypatch) -> None:
    monkeypatch.delenv("SLURM_PROCID", raising=False)
    group = [f"run_dir={tmp_path / 'run'}", "learner.hosts=2"]
    assert main(["launch", *group]) == 2
    assert "learner.hosts=2 is a learner on several machines" in capsys.readouterr().err
    assert main(["learner", *group, "learner.coordinator=127.0.0.1:1"]) == 2
    assert "give this process its place in the group with --host-index N" in capsys.readouterr().err
    assert main(["learner", "--host-index", "2", *group, "learner.coordinator=127.0.0.1:1"]) == 2
    assert "--host-index 2 is outside the group of learner.hosts = 2 (0 to 1)" in capsys.readouterr().err
    assert main(["learner", "--host-index", "1", *group]) == 2
    assert "learner.hosts = 2 needs learner.coordinator" in capsys.readouterr().err


def test_eval_video_takes_gif_webp_or_mp4(tmp_path: Path, capsys) -> None:
    assert main(["eval", "--checkpoint", str(REPO / "pretrained" / "general-s"), "--video", str(tmp_path / "a.avi")]) \
        == 2
    err = capsys.readouterr().err
    assert "--video" in err and ".gif, .webp or .mp4" in err and not (tmp_path / "a.avi").exists()


def test_eval_without_a_run_directory_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "--checkpoint", str(tmp_path)]) == 2
    assert "no config.toml" in capsys.readouterr().err


def test_resume_without_a_run_directory_is_a_usage_error(tmp_path: Path, capsys) -> None:
    assert main(["train", "--resume", str(tmp_path)]) == 2
    assert "has no config.toml" in capsys.readouterr().err


def test_config_error_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "ppo.learning_rat=1", "--print-config"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.strip() == (
        "impulse train: config error: unknown config key 'ppo.learning_rat' "
        "(from override 'ppo.learning_rat=1'); did you mean 'ppo.learning_rate'?"
    )


def test_version_and_global_options(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.startswith("impulse ")
    assert main(["--log-format", "json", "train", "--log-level", "DEBUG", "seed=2", "--print-config"]) == 0
    assert tomllib.loads(capsys.readouterr().out)["seed"] == 2


def test_stray_argument_is_a_usage_error() -> None:
    with pytest.raises(SystemExit) as info:
        main(["levels", "seed=1"])  # levels takes no config
    assert info.value.code == 2


def test_bench_unknown_name(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "nosuch"]) == 2
    err = capsys.readouterr().err
    assert "unknown benchmark 'nosuch'" in err and "engine" in err


def test_bench_help_lists_modules(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    out = capsys.readouterr().out
    assert "available benchmarks:" in out and "engine" in out and "_harness" not in out


def test_bench_runs_module_main_with_its_arguments(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    package = tmp_path / "fake_benchmarks"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "_private.py").write_text("")
    (package / "echo.py").write_text(
        "def main(argv):\n    print('ARGS', argv)\n    return 3 if '--fail' in argv else None\n"
    )
    (package / "nomain.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert bench.available("fake_benchmarks") == ["echo", "nomain"]
    assert bench.run("echo", ["--quick", "x"], package="fake_benchmarks") == 0
    assert bench.run("echo", ["--fail"], package="fake_benchmarks") == 3
    with pytest.raises(bench.UnknownBenchmark, match="no main"):
        bench.run("nomain", [], package="fake_benchmarks")
    with pytest.raises(bench.UnknownBenchmark, match="did you mean 'echo'"):
        bench.run("ecko", [], package="fake_benchmarks")


def test_distributed_commands_without_a_run_directory_are_usage_errors(tmp_path: Path, capsys) -> None:
    for argv in (["launch", "--resume", str(tmp_path)], ["learner", "--run", str(tmp_path)],
                 ["actor", "--run", str(tmp_path), "--index", "1"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "has no config.toml" in err and err.startswith(f"impulse {argv[0]}:"), err


def test_run_and_config_together_are_a_usage_error(tmp_path: Path, capsys) -> None:
    """`--run` reads the run's own config.toml; a --config beside it would be silently ignored, so it is refused."""
    config = tmp_path / "c.toml"
    config.write_text('name = "x"\n')
    for argv in (["learner", "--run", str(tmp_path), "--config", str(config)],
                 ["actor", "--run", str(tmp_path), "--config", str(config)],
                 ["curriculum", "serve", "--run", str(tmp_path), "--config", str(config)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "either --run or --config, not both" in err, err
