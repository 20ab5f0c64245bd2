"""How the solver runs: the options of a step that are not slot counts.

`SceneSizes` says how many slots a scene has (array shapes); `SolverOptions` says how the step solves them. Both
are hashable and static (compiled in), so a jitted step is compiled once per (sizes, options) pair, and a check
that two scenes fit together compares slot counts only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Schedule = Literal["phased", "jax2d", "jax2d_wipe"]
SCHEDULES: tuple[str, ...] = ("phased", "jax2d", "jax2d_wipe")
Backend = Literal["xla", "pallas", "pallas_interpret"]
BACKENDS: tuple[str, ...] = ("xla", "pallas", "pallas_interpret")


@dataclass(frozen=True)
class SolverOptions:
    """How a step solves its constraints. Hashable, so it can be a static argument of jitted functions.

    `schedule` picks the order in which contacts are visited (see docs/engine.md): "phased" (default, fastest),
    "jax2d" (Jax2D's batch order, for trajectories that follow Jax2D's closely) or "jax2d_wipe" (the same plus
    Jax2D's padding bug, which zeroes the last contact pair's impulses; only to compare trajectories with Jax2D
    and Kinetix, never to train with).
    `backend` picks how the phased schedule's iterations run: "xla" (the pure-JAX stages) or "pallas" (one fused
    kernel per block of scenes on a GPU, solver_kernel.py; the XLA stages on other platforms); "pallas_interpret"
    runs that kernel through Pallas's interpreter on any platform, to test it without a GPU.
    `iterations` is the number of solver sweeps per step and `warm_starting` whether a step starts from the
    previous step's impulses (Kinetix's `num_solver_iterations` and `do_warm_starting`).
    """

    schedule: Schedule = "phased"
    backend: Backend = "xla"
    iterations: int = 10
    warm_starting: bool = True

    def __post_init__(self) -> None:
        if self.schedule not in SCHEDULES:
            raise ValueError(f"unknown solver schedule {self.schedule!r}; choose one of {', '.join(SCHEDULES)}")
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown physics backend {self.backend!r}; choose one of {', '.join(BACKENDS)}")
        if self.backend != "xla" and self.schedule != "phased":
            raise ValueError(f"physics backend {self.backend!r} runs the phased schedule only, not {self.schedule!r}")
        if self.iterations < 1:
            raise ValueError(f"solver iterations must be >= 1, got {self.iterations}")
