"""Impulse: distributed actor-learner reinforcement learning on Kinetix-style 2D physics tasks, on its own JAX
physics engine.

The one import name of the project: its rooms are `impulse.engine`, `impulse.bus`, `impulse.curriculum`,
`impulse.monitor`, `impulse.actors`, `impulse.learner`, `impulse.studio`, `impulse.deploy` and
`impulse.benchmarks` (docs/architecture.md). In the repository they are the top-level folders, and this folder
holds a link to each (`impulse/engine -> ../engine`, ...): the package is an ordinary folder, the same installed
(the wheel copies the files), installed editable, or run from a checkout without installing (a lent GPU machine).

The public face, imported on first use so that `import impulse` stays light: `make_env` and `Env` (the environment
as a library, `impulse.engine.env.api`), `RunConfig` (the run configuration, `impulse.deploy.run_config`),
`EnvConfig` (`impulse.engine.env.config`) and `__version__`.
"""

from __future__ import annotations

import importlib
from importlib import metadata
from typing import Any

try:
    __version__ = metadata.version("impulse")
except metadata.PackageNotFoundError:  # a checkout that was never installed
    __version__ = "0+unknown"

_PUBLIC = {"RunConfig": "impulse.deploy.run_config", "EnvConfig": "impulse.engine.env.config",
           "make_env": "impulse.engine.env.api", "Env": "impulse.engine.env.api"}


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'impulse' has no attribute {name!r}")


__all__ = ["Env", "EnvConfig", "RunConfig", "__version__", "make_env"]
