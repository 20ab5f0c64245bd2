"""Kinetix's own observations of level files, made INSIDE the reference virtualenv, for the CI fixture
tests/fixtures/kinetix/observations.npz (checked by tests/engine/env/test_env_observations.py).

Like _reference_runner.py, this is the only kind of code that imports Kinetix, and it imports nothing from our
project. For every level file given, Kinetix loads it (`load_from_json_file`) and its observation classes
observe the loaded state as it is (the level's first observation):

- `symbolic_flat_padded/<level>`: `SymbolicPaddedObservations` (rows x width);
- `symbolic_flat/<level>`: `SymbolicObservations` (a vector), for comparison;
- `blind/<level>`: `BlindObservations` with the file's state at timestep `--timestep` (a one-hot of the step).

    .cache/reference-venv/bin/python benchmarks/_reference_observations.py --out FILE.npz \
        --timestep 7 ../shared/kinetix-levels/*/*.json

where <level> is "<size folder>/<file stem>". One JSON line reports what was written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from kinetix.environment.spaces import BlindObservations, SymbolicObservations, SymbolicPaddedObservations
from kinetix.util.saving import load_from_json_file

sys.path.append(str(Path(__file__).resolve().parent))
from _reference_common import emit, environment, progress  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("levels", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--timestep", type=int, default=7, help="the timestep the blind observation is made at")
    args = parser.parse_args(argv)

    arrays: dict[str, np.ndarray] = {}
    for path in args.levels:
        name = f"{path.parent.name}/{path.stem}"
        state, static_params, env_params = load_from_json_file(str(path.resolve()))
        observers = {
            "symbolic_flat_padded": SymbolicPaddedObservations(env_params, static_params),
            "symbolic_flat": SymbolicObservations(env_params, static_params),
            "blind": BlindObservations(env_params, static_params),
        }
        for kind, observer in observers.items():
            observed = state.replace(timestep=args.timestep) if kind == "blind" else state
            arrays[f"{kind}/{name}"] = np.asarray(observer.get_obs(observed))
        progress(f"{name}: padded {arrays[f'symbolic_flat_padded/{name}'].shape}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **arrays)
    emit({"written": str(args.out), "levels": len(args.levels), "timestep": args.timestep, **environment()})


if __name__ == "__main__":
    main()
