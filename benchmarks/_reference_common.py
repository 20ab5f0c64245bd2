"""Helpers shared by the scripts that run in the reference virtualenv (Jax2D and Kinetix installed, our project
not importable): JSON-line output, the shared scripted actions, and reducing Kinetix's structs to Jax2D's.

The scripts run with ``python -I``, so their folder is not on the path; each appends it (after the standard
library and site-packages, so nothing of ours can shadow an installed module) and imports this file by name.
It imports only the standard library, numpy and JAX, and loads ``scripted_actions.py`` (which is plain Python)
by path.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import sys
from functools import cache
from pathlib import Path
from types import ModuleType
from typing import Any

import jax
import numpy as np

HERE = Path(__file__).resolve().parent


def emit(record: dict[str, Any]) -> None:
    """One JSON line on stdout, flushed: the caller (benchmarks.reference_env.run_reference) reads them."""
    print(json.dumps(record), flush=True)


def progress(message: str) -> None:
    print(f"[reference] {message}", file=sys.stderr, flush=True)


def environment() -> dict[str, str]:
    """Same keys as benchmarks/_harness.environment, so records from both sides line up."""
    device = jax.devices()[0]
    return {"jax_version": jax.__version__, "backend": jax.default_backend(), "device": device.device_kind}


def level_name(path: str) -> str:
    """'s/h0_weak_thrust.json' style: the size folder plus the file name."""
    resolved = Path(path)
    return f"{resolved.parent.name}/{resolved.name}"


@cache
def scripted_actions() -> ModuleType:
    """benchmarks/scripted_actions.py: the action pattern both engines are fed."""
    spec = importlib.util.spec_from_file_location("impulse_scripted_actions", HERE / "scripted_actions.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def action_sequence(steps: int, num_joints: int, num_thrusters: int, kind: str) -> np.ndarray:
    """[steps, J + T] engine actions: zeros, or the shared scripted pattern."""
    if kind == "zero":
        return np.zeros((steps, num_joints + num_thrusters), np.float32)
    rows = [scripted_actions().engine_actions(i, num_joints, num_thrusters) for i in range(steps)]
    return np.stack(rows).reshape(steps, num_joints + num_thrusters).astype(np.float32)


def as_base(instance: Any, cls: type) -> Any:
    """Keep only the fields of a (Jax2D) base dataclass: Kinetix's EnvState/EnvParams/StaticEnvParams extend
    Jax2D's structs, and the engine comparisons carry exactly Jax2D's own state, not Kinetix's extras."""
    return cls(**{field.name: getattr(instance, field.name) for field in dataclasses.fields(cls)})
