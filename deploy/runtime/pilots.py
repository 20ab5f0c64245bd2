"""Loading a trained policy for Impulse Studio's Play page and gallery (`studio.play.Pilot`) from a run directory or
a shipped agent, as `impulse eval --checkpoint` restores it. The studio cannot read run configurations itself, so
`impulse studio` hands it `load_pilot`; `impulse bench studio` uses the same loader to measure watching."""

from __future__ import annotations

from pathlib import Path

from impulse.deploy.config import ConfigError, resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.run_dirs import locate_checkpoint
from impulse.learner.checkpoint import TRAIN
from impulse.learner.run import RunError, build, restore_policy
from impulse.studio.level_io import LevelInputError
from impulse.studio.play import Pilot


def load_pilot(checkpoint: str) -> Pilot:
    """A `studio.play.Pilot` from a run directory or one checkpoint's folder, as `impulse eval --checkpoint`
    restores it; `LevelInputError` with the reason when it cannot be loaded."""

    path = Path(checkpoint)
    try:
        run_dir, step = locate_checkpoint(path)
        config = resolve_config(RunConfig, run_dir / "config.toml", [])
        trainer, agent, _, _ = build(config)
        restored = restore_policy(config, run_dir, step, trainer)
    except (FileNotFoundError, ConfigError, RunError, ValueError) as err:
        raise LevelInputError(f"cannot load an agent from {checkpoint}: {err}") from None
    name = f"{run_dir.name} (update {restored.step})"
    return Pilot(agent, restored.items[TRAIN].params, trainer.env_params, name)
