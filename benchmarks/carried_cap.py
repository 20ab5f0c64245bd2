"""The speed of the default engine step with the carried-impulse cap as it is (`CARRIED_IMPULSE_CAP`, 64 clamp
crossings) and as it was before the articulated-body fix (1 crossing), in the same run: the cap is a constant
folded into the compiled step, so both programs are compiled here, and timed in alternation (`--rounds`) so that
a change of load hits both alike. Protocol of `impulse bench engine`: one step vmapped over `--num-envs` copies of
the size's level in a jitted scan of 100 steps, median of 3 timed calls.

Output: JSON lines (one per size, cap and round, then one ratio per size: new / old steps per second).

    impulse bench carried_cap --sizes s,l
"""

from __future__ import annotations

import argparse
import importlib
import statistics
from collections.abc import Iterator
from contextlib import contextmanager

from impulse.benchmarks._harness import DEFAULT_LEVELS, emit, environment, progress, require_levels
from impulse.benchmarks.engine import measure_ours

OLD_CAP = 1.0
MODULES = tuple(importlib.import_module(f"impulse.engine.physics.{name}")
                for name in ("params", "step", "joint_solver", "solver_kernel"))
"""The modules that read the cap (by module, not through the package, whose `step` is the function)."""


@contextmanager
def carried_cap(value: float) -> Iterator[None]:
    """Every module that reads the cap sees `value` while the step is traced (restored afterwards)."""
    before = [module.CARRIED_IMPULSE_CAP for module in MODULES]
    for module in MODULES:
        module.CARRIED_IMPULSE_CAP = value
    try:
        yield
    finally:
        for module, value_before in zip(MODULES, before, strict=True):
            module.CARRIED_IMPULSE_CAP = value_before


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench carried_cap", description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="s,l")
    parser.add_argument("--num-envs", type=int, default=1024)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args(argv)
    levels = require_levels()
    new_cap = MODULES[0].CARRIED_IMPULSE_CAP
    env = environment()
    for size in [s.strip() for s in args.sizes.split(",") if s.strip()]:
        rates: dict[float, list[float]] = {new_cap: [], OLD_CAP: []}
        for round_number in range(args.rounds):
            for cap in (new_cap, OLD_CAP):
                progress(f"{size}: cap {cap:g}, round {round_number + 1} ...")
                with carried_cap(cap):
                    measured = measure_ours(str(levels / DEFAULT_LEVELS[size]), args.num_envs, 100, 3)
                rates[cap].append(measured["steps_per_s"])
                emit({"size": size, "cap": cap, "round": round_number, "num_envs": args.num_envs, **measured, **env})
        emit({"size": size, "comparison": "new_cap/old_cap", "new_cap": new_cap, "old_cap": OLD_CAP,
              "ratio": statistics.median(rates[new_cap]) / statistics.median(rates[OLD_CAP]), **env})
