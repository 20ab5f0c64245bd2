"""Checks `impulse launch` makes before it starts anything: what every process of the run will need.

A problem that every incarnation of a process hits (a malformed level file, a checkpoint written by another
network, a missing credentials file) would otherwise surface as each child crashing at start-up, being restarted,
and crashing again, behind a status line that says "exit status 1". Found here, it is one error naming the file or
key and the problem, and nothing has been started or written.

One function per check, each raising `PreflightError`; `run_preflight` runs those the run needs, cheapest first.
The checks that need JAX (level sets, checkpoints) run it on the CPU in the launcher (`cpu_only`), so that the
launcher never takes an accelerator's memory from the processes it is about to start.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import math
import socket
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from impulse.bus.config import endpoint_parts
from impulse.bus.router import CredentialsError, client_security
from impulse.curriculum.methods import make_curriculum
from impulse.deploy.runtime import process_roles
from impulse.deploy.runtime.process_roles import LaunchPlan
from impulse.engine.env.spec import env_from_config
from impulse.engine.levels import handmade
from impulse.engine.levels.sets import HANDMADE, load_level_set
from impulse.learner.agent import make_agent
from impulse.learner.checkpoint import CURRICULUM, TRAIN, Checkpointer, CheckpointError
from impulse.learner.update import TrainState, make_optimizer
from impulse.monitor.scalars import ScalarSinkError, check_sinks

if TYPE_CHECKING:
    from impulse.deploy.run_config import RunConfig
    from impulse.engine.physics.sizes import SceneSizes
    from impulse.learner.config import CheckpointConfig

log = logging.getLogger("impulse.launch")

CURRICULUM_DIR = "curriculum"
"""The curriculum service's folder in a run directory (its checkpoints are `curriculum/<checkpoint.directory>`)."""
LONGEST_DETAIL = 1200
"""Characters of a library's error message kept in a preflight error (orbax's can list a whole tree)."""


class PreflightError(Exception):
    """A run cannot start: the message names the key or file and the problem, and is shown as it is."""


def run_preflight(config: RunConfig, run_dir: Path, *, resume: bool, curriculum_service: bool,
                  cpu_only: bool = False, init_from: Path | None = None,
                  credential_roles: Sequence[str] | None = None) -> None:
    """Every check the run needs, cheapest first; raises `PreflightError` at the first problem.

    `resume`: the run continues from `run_dir`'s checkpoints (`--resume`). `curriculum_service`: the launch starts
    the curriculum service, which always resumes from its own checkpoints when there are any. `cpu_only`: keep JAX
    in this process on the CPU (for the launcher; not for tests that share a process with others). `init_from`:
    the run directory or shipped agent whose policy a new run starts from (`--init-from`). `credential_roles`: the
    bus roles whose credentials the processes present (default: those of the processes a launch of `config`
    starts, `process_roles.credential_roles`)."""
    if credential_roles is None:
        credential_roles = process_roles.credential_roles(LaunchPlan(config, run_dir, resume=resume))
    check_credentials(config, credential_roles)
    check_hub_port(config)
    check_scalar_sinks(config)
    level_sets = [] if config.uses_curriculum_service else [("env.levels", config.env.levels)]
    if config.eval.levels and config.eval.attempts > 0:
        level_sets += [("eval.levels", source) for source in _sources(config.eval.levels)]
    level_sets += [("evaluator.levels", source) for source in _sources(config.evaluator.levels)]
    learner_checkpoints = run_dir / config.checkpoint.directory
    curriculum_checkpoints = run_dir / CURRICULUM_DIR / config.checkpoint.directory
    restores = [(learner_checkpoints, check_learner_checkpoint)] if resume else []
    if curriculum_service:
        restores.append((curriculum_checkpoints, check_curriculum_checkpoint))
    restores = [(directory, check) for directory, check in restores if _holds_entries(directory)]
    if init_from is not None and not resume:
        restores.append((init_from / config.checkpoint.directory, check_fine_tuning_source))
    if not level_sets and not restores:
        return
    if cpu_only:
        _keep_jax_on_cpu()
    for key, source in level_sets:
        check_level_set(key, source, config)
    for directory, check in restores:
        check(config, directory)


def _sources(spec: str) -> list[str]:
    """The level sets a comma-separated specification names (as `learner.scoring.set_names`, without JAX)."""
    return list(dict.fromkeys(part.strip() for part in spec.split(",") if part.strip()))


def check_hub_port(config: RunConfig) -> None:
    """On one machine (no `bus.connect`) the launcher listens on `bus.hub`; a port another process holds (a second
    run, most often) would fail deep inside zenoh, so say it here, with a free port to use instead."""
    if config.bus.connect:
        return
    protocol, host, port = endpoint_parts(config.bus.hub)
    if protocol != "tcp" or not port.isdigit():
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a port in TIME_WAIT is free for zenoh too
        try:
            probe.bind((host, int(port)))
        except OSError as err:
            if err.errno != errno.EADDRINUSE:
                return  # not ours to judge (an address this machine lacks): zenoh will say
            probe.bind((host, 0))
            free = probe.getsockname()[1]
            raise PreflightError(
                f"bus.hub {config.bus.hub} is already in use (another run on this machine?); give this run its own "
                f"hub, for example bus.hub=tcp/{host}:{free}") from None


def check_scalar_sinks(config: RunConfig) -> None:
    """What the learner's TensorBoard and W&B sinks need (tensorboardX when `monitor.tensorboard` is on, the W&B
    client when `monitor.wandb_project` is set)."""

    try:
        check_sinks(config.monitor)
    except ScalarSinkError as err:
        raise PreflightError(str(err)) from err


def check_credentials(config: RunConfig, roles: Iterable[str]) -> None:
    """With `bus.credentials` and routers to connect to (`bus.connect`, the only case in which the processes read
    credentials), each started role's files are there: what `bus.router.client_security` reads at connect time."""
    if not config.bus.credentials or not config.bus.connect:
        return

    for role in roles:
        try:
            client_security(config.bus.credentials, role)
        except CredentialsError as err:
            raise PreflightError(f"bus.credentials={config.bus.credentials}: the {role}'s credentials: {err}") \
                from None


def check_level_set(key: str, source: str, config: RunConfig) -> None:
    """Level set `source` (the value of config key `key`) loads into the run's scene sizes, as the actors (for
    env.levels) and the learner's final evaluation (for eval.levels) will load it.

    The bundled hand-made set is checked against its registry (names known, sizes fitting), which is what can go
    wrong with it: building its designs is tested code and costs seconds of eager JAX compiling on a small CPU."""
    log.info("checking %s = %s", key, source)
    sizes = _scene_sizes(config)

    if source == HANDMADE or source.startswith(HANDMADE + ":"):
        _check_handmade(key, source.partition(":")[2], sizes, config.env.size)
        return
    try:
        load_level_set(source, sizes)
    except Exception as err:  # whatever loading raises, each actor would die of it
        detail = str(err) if isinstance(err, ValueError) else f"{type(err).__name__}: {err}"
        where = key if source in detail else f"{key}={source}"
        raise PreflightError(f"{where}: {detail}") from None


def check_learner_checkpoint(config: RunConfig, directory: Path) -> None:
    """The learner's newest usable checkpoint in `directory` restores into this config's training state (network,
    optimiser state, policy version), as `impulse learner --resume` will restore it. A corrupt newest checkpoint
    is moved aside by the restore, as the learner would do."""
    log.info("checking that the learner's checkpoint in %s fits this config's network", directory)

    _restore(directory, config.checkpoint, TRAIN, _train_template(config), "cannot resume from the learner's")


def check_fine_tuning_source(config: RunConfig, directory: Path) -> None:
    """`--init-from`: the source's newest intact checkpoint (in `directory`) holds a policy of this config's
    network, as the learner will read it: as a reader, which moves nothing in the source."""
    log.info("checking the policy to start from in %s", directory)

    if not _holds_entries(directory):
        raise PreflightError(f"--init-from: no checkpoint in {directory}")
    _restore(directory, config.checkpoint, TRAIN, _train_template(config),
             "--init-from: cannot start from the source's", set_aside=False)


def _train_template(config: RunConfig) -> Any:
    """The shapes of the learner's training state (network, optimiser state, policy version) for `config`."""

    spec, _ = env_from_config(config.env)
    try:
        agent = make_agent(config.network, spec)
    except ValueError as err:
        raise PreflightError(f"network: {err}") from None
    ppo = config.ppo
    num_updates = max(1, math.ceil(config.total_env_steps / (ppo.num_envs * ppo.num_steps)))
    params = jax.eval_shape(agent.init, jax.random.PRNGKey(config.seed))  # shapes only: nothing compiles
    opt_state = jax.eval_shape(make_optimizer(ppo, num_updates).init, params)
    return TrainState(params, opt_state, jax.ShapeDtypeStruct((), np.int32))


def check_curriculum_checkpoint(config: RunConfig, directory: Path) -> None:
    """The curriculum service's newest usable checkpoint in `directory` restores into this config's curriculum
    state (method, buffer size, level sizes), as `impulse curriculum serve --resume` will restore it."""
    log.info("checking that the curriculum's checkpoint in %s fits this config", directory)

    spec, env_params = env_from_config(config.env)
    curriculum = make_curriculum(config.curriculum, spec, env_params, config.ppo.num_envs)
    template = jax.eval_shape(curriculum.init, jax.random.PRNGKey(config.seed))
    _restore(directory, dataclasses.replace(config.checkpoint, keep_best=False), CURRICULUM, template,
             "cannot resume from the curriculum's")


def _restore(directory: Path, checkpoint_config: CheckpointConfig, item: str, template: Any, what: str,
             set_aside: bool = True) -> None:
    """Restore `item` of the newest checkpoint in `directory` with `template` (`set_aside`: as
    `Checkpointer.restore`); a `CheckpointError` (no usable checkpoint, another network) becomes a `PreflightError`
    that begins with `what` and names the directory."""

    try:
        with Checkpointer(directory, checkpoint_config) as checkpoints:
            if checkpoints.latest_step() is None:
                return  # only a write that never finished: the service starts fresh, as it would here
            checkpoints.restore({item: template}, set_aside=set_aside)
    except (CheckpointError, OSError) as err:
        detail = str(err)
        if len(detail) > LONGEST_DETAIL:
            detail = detail[:LONGEST_DETAIL - 3] + "..."
        if str(directory.absolute()) not in detail:
            detail = f"{directory}: {detail}"
        raise PreflightError(f"{what} checkpoint: {detail}") from None


def _check_handmade(key: str, picked: str, sizes: SceneSizes, size_name: str) -> None:
    """The checks `engine.levels.sets` makes of a hand-made set before building it."""

    available = handmade.names()
    names = [name for name in picked.split(",") if name]
    unknown = [name for name in names if name not in available]
    if unknown:
        raise PreflightError(f"{key}: unknown hand-made level(s) {', '.join(unknown)}; available: "
                             f"{', '.join(available)}")
    too_large = [name for name in names if not handmade.size_of(name).fits_in(sizes)]
    if too_large:
        raise PreflightError(f"{key}: hand-made level(s) {', '.join(too_large)} too large for env.size={size_name}")
    if not names and not any(handmade.size_of(name).fits_in(sizes) for name in available):
        raise PreflightError(f"{key}: no hand-made level fits env.size={size_name}")


def _scene_sizes(config: RunConfig) -> SceneSizes:
    spec, _ = env_from_config(config.env)
    return spec.sizes


def _holds_entries(directory: Path) -> bool:
    """Whether a checkpoint directory exists and holds anything (opening a `Checkpointer` would create it)."""
    return directory.is_dir() and any(directory.iterdir())


def _keep_jax_on_cpu() -> None:
    """Make this process's JAX use the CPU, unless it has already started a backend (then it is too late, and
    whatever started it chose)."""
    try:
        from jax._src import xla_bridge

        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):  # a JAX without this private helper: leave the choice to it
        return
    if not started:
        jax.config.update("jax_platforms", "cpu")
