"""`impulse launch` fails fast: what every process would die of is found before anything starts
(`deploy.runtime.preflight`), and processes that keep failing the same way stop the run instead of crash-looping
(`deploy.runtime.supervisor`).

The launches here are real (`python -m impulse.deploy.cli launch` on configs/quick-launch.toml, their own hub port); the
preflight checks of checkpoints run in this process on checkpoints written from zeros (no training)."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from impulse.deploy.config import config_to_toml, resolve_config, write_resolved_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.preflight import PreflightError, run_preflight
from impulse.learner.checkpoint import CURRICULUM, TRAIN, Checkpointer
from tests.support.launch_procs import QUICK_LAUNCH, REPO, free_port, service_pids

ROLES = ("learner", "actor", "curriculum")


def launch(run_dir: Path, *overrides: str, env: dict[str, str] | None = None,
           timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "impulse.deploy.cli", "launch", "--config", str(QUICK_LAUNCH),
               "--status-every", "2", f"run_dir={run_dir}", f"name={run_dir.name}",
               f"bus.hub=tcp/127.0.0.1:{free_port()}", *overrides]
    environment = {**os.environ, "IMPULSE_CACHE_DIR": str(REPO / ".cache"), **(env or {})}
    return subprocess.run(command, cwd=REPO, env=environment, capture_output=True, text=True, timeout=timeout_s,
                          check=False)


def config_for(run_dir: Path, *overrides: str) -> RunConfig:
    """The quick launch's config on a free hub port (the default one may be another run's on this machine)."""
    return resolve_config(RunConfig, QUICK_LAUNCH, [f"run_dir={run_dir}", f"name={run_dir.name}",
                                                    f"bus.hub=tcp/127.0.0.1:{free_port()}", *overrides])


def zeros_like(template):
    return jax.tree.map(lambda leaf: np.zeros(leaf.shape, leaf.dtype), template)


@pytest.mark.heavy
def test_a_malformed_level_file_stops_the_launch_before_anything_starts(tmp_path: Path) -> None:
    levels = tmp_path / "truncated.json"
    levels.write_text('{"env_state": {"polygon": [')
    run_dir = tmp_path / "run"
    result = launch(run_dir, f"env.levels={levels}")
    assert result.returncode == 1, result.stderr
    error = [line for line in result.stderr.splitlines() if line.startswith("impulse launch:")]
    assert len(error) == 1 and str(levels) in error[0] and "not valid JSON" in error[0], result.stderr
    assert not run_dir.exists(), "the launcher wrote or started something"
    assert not any(service_pids(run_dir, role) for role in ROLES)


@pytest.mark.heavy
def test_actors_that_fail_the_same_way_stop_the_run(tmp_path: Path) -> None:
    """Every actor exits 2 at start-up (an actor device that CUDA_VISIBLE_DEVICES does not show, which preflight
    does not check): after 3 identical failures each the launcher stops the run and exits 1 saying why; the
    learner, stopped before its first update, writes no checkpoint."""
    run_dir = tmp_path / "run"
    result = launch(run_dir, "actors.devices=[3]", env={"CUDA_VISIBLE_DEVICES": "0"}, timeout_s=180.0)
    assert result.returncode == 1, result.stderr[-3000:]
    error = [line for line in result.stderr.splitlines() if line.startswith("impulse launch:")]
    assert len(error) == 1, result.stderr[-3000:]
    assert error[0].startswith("impulse launch: stopped the run: actor-0 and actor-1 each failed 3 times in a row the "
                               "same way: exit status 2: impulse actor: actors.devices: device 3 asked for"), error
    assert "gave up after 3 identical failures" in result.stderr
    checkpoints = run_dir / "checkpoints"
    assert not checkpoints.exists() or not any(checkpoints.iterdir()), "a checkpoint of update 0"
    assert not any(service_pids(run_dir, role) for role in ROLES)


def test_resume_with_another_network_is_refused_naming_the_checkpoint_directory(tmp_path: Path) -> None:
    from impulse.engine.env.spec import env_from_config
    from impulse.learner.agent import make_agent
    from impulse.learner.update import TrainState, make_optimizer

    run_dir = tmp_path / "run"
    config = config_for(run_dir)
    write_resolved_config(config, run_dir)
    other = dataclasses.replace(config, network=dataclasses.replace(config.network, width=32))
    spec, _ = env_from_config(other.env)
    params = jax.eval_shape(make_agent(other.network, spec).init, jax.random.PRNGKey(0))
    state = TrainState(params, jax.eval_shape(make_optimizer(other.ppo, 1).init, params),
                       jax.ShapeDtypeStruct((), np.int32))
    with Checkpointer(run_dir / "checkpoints", config.checkpoint) as checkpoints:
        checkpoints.save(5, {TRAIN: zeros_like(state)}, {"update": 5, "env_steps": 20480}, config_to_toml(other))

    with pytest.raises(PreflightError) as refused:
        run_preflight(config, run_dir, resume=True, curriculum_service=False)
    message = str(refused.value)
    assert "learner's checkpoint" in message and str((run_dir / "checkpoints").absolute()) in message
    assert "(32,) in the checkpoint, (64,) here" in message
    run_preflight(other, run_dir, resume=True, curriculum_service=False)  # the network it was written with


def test_a_curriculum_checkpoint_of_another_buffer_size_is_refused(tmp_path: Path) -> None:
    """The curriculum service always resumes its own checkpoints, so they are checked without --resume too."""
    from impulse.curriculum.methods import make_curriculum
    from impulse.engine.env.spec import env_from_config

    run_dir = tmp_path / "run"
    config = config_for(run_dir, "env.levels=random", "curriculum=plr", "curriculum.buffer_size=16")
    spec, env_params = env_from_config(config.env)
    state = jax.eval_shape(make_curriculum(config.curriculum, spec, env_params, config.ppo.num_envs).init,
                           jax.random.PRNGKey(0))
    directory = run_dir / "curriculum" / "checkpoints"
    with Checkpointer(directory, dataclasses.replace(config.checkpoint, keep_best=False)) as checkpoints:
        checkpoints.save(3, {CURRICULUM: zeros_like(state)}, {"samples": 3}, config_to_toml(config))

    bigger = config_for(run_dir, "env.levels=random", "curriculum=plr", "curriculum.buffer_size=32")
    with pytest.raises(PreflightError, match="curriculum's checkpoint") as refused:
        run_preflight(bigger, run_dir, resume=False, curriculum_service=True)
    assert str(directory.absolute()) in str(refused.value)
    run_preflight(config, run_dir, resume=False, curriculum_service=True)


def test_level_set_names_and_credentials_are_checked(tmp_path: Path) -> None:
    with pytest.raises(PreflightError, match="^env.levels: unknown hand-made level\\(s\\) s_nope; available: "):
        run_preflight(config_for(tmp_path, "env.levels=handmade:s_nope"), tmp_path, resume=False,
                      curriculum_service=False)
    with pytest.raises(PreflightError, match="^eval.levels: .*nowhere.json"):
        run_preflight(config_for(tmp_path, f"eval.levels={tmp_path / 'nowhere.json'}"), tmp_path, resume=False,
                      curriculum_service=False)
    secrets = tmp_path / "secrets"
    remote = ("bus.connect=['tcp/127.0.0.1:7447']", f"bus.credentials={secrets}")
    with pytest.raises(PreflightError, match=f"^bus.credentials={secrets}: the learner's credentials: .*does not "
                                             "exist"):
        run_preflight(config_for(tmp_path, *remote), tmp_path, resume=False, curriculum_service=False)
    secrets.mkdir()
    (secrets / "learner.password").write_text("x\n")
    with pytest.raises(PreflightError, match="the actor's credentials: .*neither ca.pem nor actor.password"):
        run_preflight(config_for(tmp_path, *remote), tmp_path, resume=False, curriculum_service=False)


def test_a_hub_port_in_use_is_one_clear_error_with_a_free_port_to_use(tmp_path: Path) -> None:
    import re
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = config_for(tmp_path / "run", f"bus.hub=tcp/127.0.0.1:{port}")
        with pytest.raises(PreflightError, match=f"bus.hub tcp/127.0.0.1:{port} is already in use") as raised:
            run_preflight(config, tmp_path / "run", resume=False, curriculum_service=False)
        suggested = int(re.search(r"bus.hub=tcp/127.0.0.1:(\d+)", str(raised.value)).group(1))
        assert suggested != port
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", suggested))  # free when suggested (nothing else took it since)
    run_preflight(config_for(tmp_path / "run", f"bus.hub=tcp/127.0.0.1:{port}"), tmp_path / "run", resume=False,
                  curriculum_service=False)  # the port is free again: no complaint
