"""Which GPUs a process sees, set before JAX starts.

JAX's GPU backend opens, and preallocates memory on, every GPU the process can see. A learner and several actors
sharing a multi-GPU machine must therefore each see only their own GPUs: `restrict_gpus` narrows
CUDA_VISIBLE_DEVICES before JAX first touches a device. Positions count among the GPUs the process may see already,
so they compose with a job scheduler that hands the job a subset (SLURM sets CUDA_VISIBLE_DEVICES to it).
On a machine without GPUs the variable is ignored by JAX and nothing changes.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping, Sequence

VISIBLE = "CUDA_VISIBLE_DEVICES"


def visible_gpus(positions: Sequence[int], inherited: str | None) -> str:
    """The CUDA_VISIBLE_DEVICES value that shows only the GPUs at `positions` among those `inherited` shows
    (every GPU when unset). Raises ValueError naming the problem when a position is not there."""
    if inherited is None or not inherited.strip():
        return ",".join(str(p) for p in positions)
    available = [gpu.strip() for gpu in inherited.split(",") if gpu.strip()]
    missing = [p for p in positions if p >= len(available)]
    if missing:
        raise ValueError(f"device {missing[0]} asked for, but {VISIBLE}={inherited!r} shows only "
                         f"{len(available)} GPU(s), numbered 0..{len(available) - 1} here")
    return ",".join(available[p] for p in positions)


def restrict_gpus(positions: Sequence[int], environ: MutableMapping[str, str] = os.environ) -> str | None:
    """Let this process see only the GPUs at `positions` (nothing to do when empty); returns the value set.

    Must run before JAX first touches a device: the CUDA driver reads the variable once, when it starts."""
    if not positions:
        return None
    value = visible_gpus(positions, environ.get(VISIBLE))
    environ[VISIBLE] = value
    return value
