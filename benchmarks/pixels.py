"""Pixel observations against Kinetix 3.0.2's: the same images, and env speed with pixel observations.

Images. For every shared level, both sides load the file, take single engine steps (no frame skip) under the
shared scripted engine actions (benchmarks/scripted_actions.py, as benchmarks/compat_jax2d.py does) and draw the
pixel observation (``--downscale``, both sides; 4 by default: 125 x 125) at the recorded step counts. Two
comparisons per level and step:
- ``full``: our engine and our renderer against Kinetix's engine (Jax2D) and its renderer; after step 0 the
  engines' small differences (see compat_jax2d) also move pixels;
- ``renderer``: our renderer drawing Kinetix's own state (its body positions and rotations, joint and thruster
  world positions put into our state) against Kinetix's image: the renderers alone.
A pixel differs when any channel differs by more than 1e-6; each differing pixel is put in one class, first
match wins: ``thruster`` (within the thruster glyph's window), ``joint`` (within the joint glyph, plus 1 px),
``edge`` (Kinetix's image is not uniform in the pixel's 3 x 3 neighbourhood: a shape boundary, where a float
rounding difference flips a pixel), ``interior`` (anything else: a real disagreement).

Speed. Env steps/s with pixel observations, ours against Kinetix's pixel env in the same run: a jitted
``lax.scan`` of the vmapped env step with uniform random multi-discrete actions, frame skip 2, auto-reset; each
step's image is summed into a checksum so that the rendering cannot be optimised away (on both sides).

Prints JSON lines: per (level, step) records, a summary per comparison, then speed records and their ratio.

    impulse bench pixels                                   # all 42 levels, steps 0,10,30; speed on S, 256 envs
    impulse bench pixels --levels 's/*' --record 0,30 --no-speed
    impulse bench pixels --no-images --sizes s,m --num-envs 64
    impulse bench pixels --levels 's/*' --downscale 2 --no-speed
"""

from __future__ import annotations

import argparse
import functools
import tempfile
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from impulse.benchmarks import env as env_bench
from impulse.benchmarks._harness import DEFAULT_LEVELS, emit, environment, progress, require_levels
from impulse.benchmarks.compat_jax2d import action_sequence, level_name, resolve_levels
from impulse.engine.env.pixels import pixel_geometry, render_pixels
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.levels.level import Level
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState
from impulse.engine.physics.step import step

SCRIPT = Path(__file__).resolve().parent / "_reference_pixels.py"
DEFAULT_DOWNSCALE = 4
PIXEL_TOLERANCE = 1e-6
CLASSES = ("thruster", "joint", "edge", "interior")


# --- Comparison (pure numpy) --------------------------------------------------------------------------------

def differing(ours: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """[W, H] true where any channel differs by more than PIXEL_TOLERANCE."""
    return np.any(np.abs(ours - reference) > PIXEL_TOLERANCE, axis=-1)


def not_uniform(image: np.ndarray) -> np.ndarray:
    """[W, H] true where the 3 x 3 neighbourhood (clipped at the border) holds more than one colour."""
    padded = np.pad(image, ((1, 1), (1, 1), (0, 0)), mode="edge")
    w, h = image.shape[:2]
    varied = np.zeros((w, h), bool)
    for dx in (0, 1, 2):
        for dy in (0, 1, 2):
            varied |= np.any(padded[dx:dx + w, dy:dy + h] != image, axis=-1)
    return varied


def near_points(points: np.ndarray, radius: float, shape: tuple[int, int]) -> np.ndarray:
    """[W, H] true within `radius` pixels (Chebyshev) of any of `points` [n, 2] (image pixel coordinates)."""
    xs, ys = np.arange(shape[0])[:, None, None], np.arange(shape[1])[None, :, None]
    if len(points) == 0:
        return np.zeros(shape, bool)
    px, py = points[:, 0][None, None, :], points[:, 1][None, None, :]
    return np.any((np.abs(xs - px) <= radius) & (np.abs(ys - py) <= radius), axis=-1)


def classify(
    diff: np.ndarray, reference: np.ndarray, joints: np.ndarray, thrusters: np.ndarray, downscale: int
) -> dict[str, int]:
    """Count differing pixels per class (see the module docstring); joints and thrusters are image pixels."""
    geometry = pixel_geometry(downscale)
    zones = {
        "thruster": near_points(thrusters, geometry.thruster_window / 2 + 1, diff.shape),
        "joint": near_points(joints, geometry.joint_pixels // 2 + 1, diff.shape),
        "edge": not_uniform(reference),
    }
    left = diff.copy()
    counts = {}
    for name in CLASSES[:-1]:
        hit = left & zones[name]
        counts[name] = int(hit.sum())
        left &= ~hit
    counts["interior"] = int(left.sum())
    return counts


def compare_images(
    ours: np.ndarray, reference: np.ndarray, joints: np.ndarray, thrusters: np.ndarray, downscale: int
) -> dict:
    diff = differing(ours, reference)
    gap = np.abs(ours - reference).max(axis=-1)
    return {
        "pixels": int(diff.size),
        "differing": int(diff.sum()),
        "fraction": float(diff.mean()),
        "mean_abs_of_differing": float(gap[diff].mean()) if diff.any() else 0.0,
        "max_abs": float(gap.max()),
        "classes": classify(diff, reference, joints, thrusters, downscale),
    }


def image_points(world: np.ndarray, active: np.ndarray, downscale: int) -> np.ndarray:
    """World positions [n, 2] of active items as (rounded) image pixel coordinates."""
    ppm = pixel_geometry(downscale).pixels_per_metre
    return np.round(np.asarray(world, np.float64)[np.asarray(active, bool)] * ppm).astype(int).reshape(-1, 2)


# --- Our side --------------------------------------------------------------------------------------------------

@functools.partial(jax.jit, static_argnames=("sizes", "record"))
def _our_states(state: SimState, params: Any, actions: jax.Array, sizes: SceneSizes, record: tuple[int, ...]):
    """Our states after each engine step, kept at the `record` step counts (0 = the level itself)."""

    def body(s, a):
        s, _ = step(s, params, a, sizes)
        return s, s

    _, states = jax.lax.scan(body, state, actions)
    states = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, states)
    return jax.tree.map(lambda x: x[jnp.asarray(record)], states)


@functools.partial(jax.jit, static_argnames=("sizes", "downscale"))
def _render(state: SimState, level: Level, sizes: SceneSizes, downscale: int) -> jax.Array:
    return render_pixels(state, level, sizes, downscale)


def with_reference_pose(state: SimState, reference: dict[str, np.ndarray]) -> SimState:
    """Our state with Kinetix's body poses and joint/thruster world positions: what its renderer read."""
    return state.replace(
        bodies=state.bodies.replace(position=jnp.asarray(reference["position"]),
                                    rotation=jnp.asarray(reference["rotation"])),
        joints=state.joints.replace(global_position=jnp.asarray(reference["joint_position"]).reshape(-1, 2)),
        thrusters=state.thrusters.replace(
            global_position=jnp.asarray(reference["thruster_position"]).reshape(-1, 2)),
    )


def compare_level(
    path: Path, record: tuple[int, ...], reference: dict[str, np.ndarray], downscale: int
) -> list[dict]:
    loaded = load_kinetix_level(path)
    sizes, level = loaded.sizes, loaded.level
    actions = np.zeros((0, sizes.num_joints + sizes.num_thrusters), np.float32)  # only the level itself
    if max(record):
        actions = action_sequence(max(record), sizes.num_joints, sizes.num_thrusters, "scripted")
    states = _our_states(level.state, loaded.params, jnp.asarray(actions), sizes, record)
    records = []
    for i, count in enumerate(record):
        key = f"{level_name(path)}@{count}"
        ref = {name: reference[f"{key}/{name}"] for name in
               ("image", "global_info", "position", "rotation", "joint_position", "thruster_position")}
        ours_state = jax.tree.map(lambda x, i=i: x[i], states)
        joints = image_points(ref["joint_position"], ours_state.joints.active, downscale)
        thrusters = image_points(ref["thruster_position"], ours_state.thrusters.active, downscale)
        full = np.asarray(_render(ours_state, level, sizes, downscale))
        posed = np.asarray(_render(with_reference_pose(ours_state, ref), level, sizes, downscale))
        gravity = np.asarray(ours_state.gravity[1:2] / 10.0)
        records.append({
            "benchmark": "pixels", "level": level_name(path), "step": count, "downscale": downscale,
            "full": compare_images(full, ref["image"], joints, thrusters, downscale),
            "renderer": compare_images(posed, ref["image"], joints, thrusters, downscale),
            "global_info_equal": bool(np.allclose(gravity, ref["global_info"])),
        })
    return records


def summarise(records: list[dict], which: str) -> dict:
    total = sum(r[which]["pixels"] for r in records)
    differing_total = sum(r[which]["differing"] for r in records)
    classes = {name: sum(r[which]["classes"][name] for r in records) for name in CLASSES}
    by_step: dict[int, list[float]] = {}
    for r in records:
        by_step.setdefault(r["step"], []).append(r[which]["fraction"])
    return {
        "benchmark": "pixels", "summary": which, "images": len(records), "fraction": differing_total / max(total, 1),
        "identical_images": sum(r[which]["differing"] == 0 for r in records),
        "worst": max(records, key=lambda r: r[which]["fraction"])["level"] if records else None,
        "worst_fraction": max((r[which]["fraction"] for r in records), default=0.0),
        "fraction_by_step": {str(k): float(np.mean(v)) for k, v in sorted(by_step.items())},
        "classes": classes, **environment(),
    }


def run_images(paths: list[Path], record: tuple[int, ...], downscale: int) -> None:
    from impulse.benchmarks.reference_env import run_reference

    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "kinetix_pixels.npz"
        args = ["render", "--levels", *map(str, paths), "--record", ",".join(map(str, record)), "--out", str(out),
                "--downscale", str(downscale)]
        run_reference(args, timeout=3600, script=SCRIPT)
        with np.load(out) as data:
            reference = {name: data[name] for name in data.files}
    records: list[dict] = []
    for path in paths:
        progress(f"pixels: {level_name(path)} ...")
        for record_line in compare_level(path, record, reference, downscale):
            emit(record_line)
            records.append(record_line)
    for which in ("full", "renderer"):
        emit(summarise(records, which))


# --- Speed -----------------------------------------------------------------------------------------------------

def measure_ours(size: str, num_envs: int, num_steps: int, repeats: int, downscale: int) -> dict:
    """Env steps/s with pixel observations, every image kept (summed) so none of the drawing can be skipped."""
    return env_bench.measure_ours(size, num_envs, num_steps, repeats, observation="pixels", pixel_downscale=downscale,
                                  keep=lambda obs, reward: obs.image.sum())


def measure_reference(size: str, num_envs: int, num_steps: int, repeats: int, downscale: int) -> dict:
    from impulse.benchmarks.reference_env import ReferenceEnvError, run_reference

    level = str(require_levels() / DEFAULT_LEVELS[size])
    args = ["env-speed", "--level", level, "--num-envs", str(num_envs), "--steps", str(num_steps),
            "--repeats", str(repeats), "--downscale", str(downscale)]
    try:
        records = [r for r in run_reference(args, timeout=3600, script=SCRIPT) if r.get("system") == "kinetix-env"]
    except ReferenceEnvError as error:
        return {"system": "kinetix-env", "error": str(error).splitlines()[0]}
    if len(records) != 1:
        return {"system": "kinetix-env", "error": f"expected one kinetix-env record, got {len(records)}"}
    return records[0]


def run_speed(
    sizes: list[str], env_counts: list[int], num_steps: int, repeats: int, reference: bool, downscale: int
) -> None:
    env_info = environment()
    for size in sizes:
        for num_envs in env_counts:
            progress(f"pixels speed: size {size}, {num_envs} envs ...")
            ours = measure_ours(size, num_envs, num_steps, repeats, downscale)
            emit({"system": "impulse-env", "size": size, "num_envs": num_envs, "steps": num_steps,
                  "observation": "pixels", "downscale": downscale, "action": "multi_discrete", "frame_skip": 2,
                  **ours, **env_info})
            if not reference:
                continue
            ref = measure_reference(size, num_envs, num_steps, repeats, downscale)
            emit({**ref, "size": size})
            if "error" in ref:
                continue
            emit({"comparison": "impulse-env/kinetix-env", "observation": "pixels", "size": size,
                  "num_envs": num_envs, "speedup": ours["steps_per_s"] / ref["steps_per_s"],
                  "compile_ratio": ours["compile_s"] / ref["compile_s"], **env_info})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="impulse bench pixels", description=__doc__.split("\n")[0])
    parser.add_argument("--levels", default="", help="comma-separated globs or names (default: all levels)")
    parser.add_argument("--record", default="0,10,30", help="engine step counts at which to compare images")
    parser.add_argument("--sizes", default="s", help="speed: comma-separated sizes among s,m,l")
    parser.add_argument("--num-envs", default="256", help="speed: comma-separated batch sizes")
    parser.add_argument("--steps", type=int, default=16, help="speed: env steps per timed scan")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--downscale", type=int, default=DEFAULT_DOWNSCALE, help="Kinetix's downscale (both sides)")
    parser.add_argument("--no-images", action="store_true", help="skip the image comparison")
    parser.add_argument("--no-speed", action="store_true", help="skip the speed comparison")
    parser.add_argument("--no-reference", action="store_true", help="speed: ours only")
    args = parser.parse_args(argv)

    require_levels()
    if not args.no_images:
        record = tuple(sorted({int(x) for x in args.record.split(",") if x.strip()}))
        run_images(resolve_levels(args.levels), record, args.downscale)
    if not args.no_speed:
        run_speed(args.sizes.split(","), [int(n) for n in args.num_envs.split(",")], args.steps, args.repeats,
                  not args.no_reference, args.downscale)


if __name__ == "__main__":
    main()
