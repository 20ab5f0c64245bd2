"""Impulse: distributed actor-learner reinforcement learning on Kinetix-style 2D physics tasks, on its own JAX
physics engine.

The one import name of the project: its rooms are `impulse.engine`, `impulse.bus`, `impulse.curriculum`,
`impulse.monitor`, `impulse.actors`, `impulse.learner`, `impulse.studio`, `impulse.deploy` and
`impulse.benchmarks` (docs/architecture.md). In the repository they are the top-level folders, mapped under this
package by the installation (pyproject.toml's `package-dir`); run from a checkout without installing (a lent GPU
machine), this package finds them beside itself.

The public face, imported on first use so that `import impulse` stays light: `make_env` and `Env` (the environment
as a library, `impulse.engine.env.api`), `RunConfig` (the run configuration, `impulse.deploy.run_config`),
`EnvConfig` (`impulse.engine.env.config`) and `__version__`.
"""

from __future__ import annotations

from importlib import metadata
from pathlib import Path
from typing import Any

_CHECKOUT = Path(__file__).resolve().parent.parent
if (_CHECKOUT / "deploy" / "cli.py").is_file() and (_CHECKOUT / "engine" / "__init__.py").is_file():
    __path__.append(str(_CHECKOUT))  # a checkout: the rooms are the folders beside this one

try:
    __version__ = metadata.version("impulse")
except metadata.PackageNotFoundError:  # a checkout that was never installed
    __version__ = "0+unknown"

_PUBLIC = {"RunConfig": "impulse.deploy.run_config", "EnvConfig": "impulse.engine.env.config",
           "make_env": "impulse.engine.env.api", "Env": "impulse.engine.env.api"}


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        import importlib

        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'impulse' has no attribute {name!r}")


__all__ = ["Env", "EnvConfig", "RunConfig", "__version__", "make_env"]
