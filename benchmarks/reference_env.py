"""The reference systems' own virtualenv: Jax2D 1.0.2 and Kinetix 3.0.2, installed with *our* JAX version.

Why a separate virtualenv: Kinetix 3.0.2 pins jax2d 1.0.1 and an old JAX, and jax2d 1.0.1 breaks on new JAX (a
removed ``clip`` keyword). Speed claims are only meaningful as ratios measured in the same run, on the same
machine, with the same JAX, so this module builds a venv beside the project (``<repo>/.cache/reference-venv``)
with the calling interpreter's exact JAX/jaxlib version plus the dependencies that Jax2D and Kinetix import,
and then installs ``jax2d==1.0.2`` and ``kinetix-env==3.0.2`` with ``--no-deps`` so their stale pins are
ignored. Our code never imports Jax2D or Kinetix: it runs ``benchmarks/_reference_runner.py`` in that venv and
reads JSON lines from its stdout (``run_reference``).

Stdlib only, so it imports from our project and also runs as a script::

    python benchmarks/reference_env.py            # build (if needed) and print the reference python's path
    python benchmarks/reference_env.py --force    # rebuild from scratch
    python benchmarks/reference_env.py engine-speed --level L.json --num-envs 1024 --steps 100

Extra pip arguments (for an offline machine, e.g. ``--no-index --find-links /path/to/wheels``) can be given in
the environment variable ``IMPULSE_REFERENCE_PIP_ARGS``.

Where a venv cannot see the machine's JAX (a lent GPU machine, whose JAX with CUDA lives in a venv of its own and
cannot be fetched again), ``IMPULSE_REFERENCE_SITE`` names a folder into which Jax2D, Kinetix and what they need
beyond that machine's packages were installed with ``pip install --target`` (``tools/gpu_bundle.py`` prepares
the wheels). The runner then runs on the calling interpreter, with that folder on its path and no venv.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import importlib.metadata
import json
import os
import shlex
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
VENV_DIR = REPO / ".cache" / "reference-venv"
STAMP_NAME = "impulse-reference-stamp.json"
LOG_NAME = "impulse-reference-install.log"
RUNNER = Path(__file__).resolve().parent / "_reference_runner.py"

# Bump when the package list below changes, so existing venvs are rebuilt.
RECIPE_VERSION = 1
# What Jax2D and Kinetix import at run time (their own pins are ignored: see the module docstring). zarr and
# numcodecs are held at the last releases that still install and import cleanly beside new numpy.
DEPENDENCIES = [
    "flax", "chex", "gymnax", "six", "jaxgl", "distrax", "safetensors", "wandb", "imageio", "pillow",
    "omegaconf", "grain", "zarr==2.18.3", "numcodecs==0.13.1",
]
REFERENCE_PACKAGES = ["jax2d==1.0.2", "kinetix-env==3.0.2"]
# Accelerator plugins present in the caller are mirrored at the same version, so the reference runs on the
# same backend as our engine (the CUDA runtime wheels are named nvidia-*).
MIRRORED_PREFIXES = ("jax-cuda", "jax-rocm", "nvidia-")
PIP_TAIL_LINES = 40
PIP_NOISE = "WARNING: Location 'file:"
SITE_ENV = "IMPULSE_REFERENCE_SITE"


class ReferenceEnvError(RuntimeError):
    """The reference venv could not be built or the reference runner failed."""


def _progress(message: str) -> None:
    print(f"[reference-env] {message}", file=sys.stderr, flush=True)


def _caller_version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def _mirrored_accelerator_packages() -> list[str]:
    """Pinned requirements for the caller's JAX accelerator plugins and CUDA runtime wheels (empty on CPU)."""
    pins = set()
    for dist in importlib.metadata.distributions():
        name = (dist.metadata["Name"] or "").lower().replace("_", "-")
        if name.startswith(MIRRORED_PREFIXES):
            pins.add(f"{name}=={dist.version}")
    return sorted(pins)


def _venv_python(venv: Path) -> Path:
    return venv / "bin" / "python"


def _wanted_stamp(jax_version: str, jaxlib_version: str, accelerator: list[str]) -> dict[str, Any]:
    return {
        "recipe": RECIPE_VERSION,
        "jax": jax_version,
        "jaxlib": jaxlib_version,
        "accelerator_packages": accelerator,
        "python": f"{sys.version_info.major}.{sys.version_info.minor}.{sys.version_info.micro}",
        "base_python": str(Path(sys.executable).resolve()),
    }


def _read_stamp(venv: Path) -> dict[str, Any] | None:
    try:
        return json.loads((venv / STAMP_NAME).read_text())
    except (OSError, ValueError):
        return None


@contextlib.contextmanager
def _lock(venv: Path) -> Iterator[None]:
    """Serialise builders: two benchmark processes starting at once must not install into the same venv."""
    venv.parent.mkdir(parents=True, exist_ok=True)
    with open(venv.parent / f"{venv.name}.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _run_logged(command: list[str], log: Path, what: str) -> str:
    """Run a command, appending its output to the install log; on failure raise with the tail of that output
    (pip's last lines name the package that failed). Returns the command's output."""
    _progress(f"{what}: {shlex.join(command)}")
    start = time.perf_counter()
    result = subprocess.run(
        command, check=False, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
        text=True, env=_clean_environment(),
    )
    with open(log, "a") as handle:
        handle.write(f"\n$ {shlex.join(command)}\n{result.stdout}")
    if result.returncode != 0:
        # pip repeats a harmless "Location 'file:///...' is ignored" warning per package: keep it out.
        lines = [line for line in result.stdout.splitlines() if not line.startswith(PIP_NOISE)]
        tail = "\n".join(lines[-PIP_TAIL_LINES:])
        raise ReferenceEnvError(
            f"{what} failed (exit {result.returncode}); last {PIP_TAIL_LINES} lines (full log: {log}):\n"
            f"{tail}"
        )
    _progress(f"{what}: done in {time.perf_counter() - start:.1f}s")
    return result.stdout


def _extra_pip_args() -> list[str]:
    return shlex.split(os.environ.get("IMPULSE_REFERENCE_PIP_ARGS", ""))


def _build(venv: Path, stamp: dict[str, Any]) -> None:
    if venv.exists():
        _progress(f"removing stale reference venv at {venv}")
        shutil.rmtree(venv)
    started = time.perf_counter()
    log = venv.parent / LOG_NAME
    log.write_text(f"reference venv build, stamp {json.dumps(stamp)}\n")
    _progress(f"creating {venv} (log: {log})")
    _run_logged([sys.executable, "-m", "venv", str(venv)], log, "venv")
    python = str(_venv_python(venv))
    pip = [python, "-m", "pip", "install", "--disable-pip-version-check", "--no-input", *_extra_pip_args()]
    base = [f"jax=={stamp['jax']}", f"jaxlib=={stamp['jaxlib']}", *stamp["accelerator_packages"]]
    _run_logged([*pip, *base, *DEPENDENCIES], log, f"pip install jax=={stamp['jax']} and dependencies")
    _run_logged([*pip, "--no-deps", *REFERENCE_PACKAGES], log, "pip install --no-deps jax2d, kinetix-env")
    check = (
        "import importlib.metadata as m, jax, jax2d, kinetix, kinetix.environment;"
        "print(jax.__version__, m.version('jax2d'), m.version('kinetix-env'))"
    )
    found = _run_logged([python, "-I", "-c", check], log, "import check (jax, jax2d, kinetix)").split()[-3:]
    if found[:1] != [stamp["jax"]]:
        raise ReferenceEnvError(f"reference venv has jax {found[:1]}, wanted {stamp['jax']} (see {log})")
    (venv / STAMP_NAME).write_text(json.dumps({**stamp, "installed": found}, indent=1) + "\n")
    elapsed = time.perf_counter() - started
    _progress(f"reference venv ready in {elapsed:.0f}s: jax, jax2d, kinetix-env = {found}")


def reference_site() -> Path | None:
    """The ``IMPULSE_REFERENCE_SITE`` folder, checked, or None when the reference runs in its venv."""
    site = os.environ.get(SITE_ENV)
    if not site:
        return None
    path = Path(site).expanduser()
    missing = [package for package in ("jax2d", "kinetix") if not (path / package).is_dir()]
    if missing:
        raise ReferenceEnvError(f"{SITE_ENV}={site} holds no {' and no '.join(missing)} package: install the "
                                "reference wheels there with pip install --target (see docs/gpu.md)")
    return path


def ensure_reference_env(jax_version: str | None = None, force: bool = False) -> Path:
    """Return the reference venv's python, building the venv first if it is missing, incomplete (no stamp) or
    was built for another JAX version, recipe or base interpreter; with ``IMPULSE_REFERENCE_SITE`` set, the
    calling interpreter (the reference then runs on the very same JAX).

    ``jax_version`` defaults to the JAX installed beside the calling interpreter, which is the point: the
    reference must run on the same JAX as our engine for same-run ratios to mean anything.
    """
    if reference_site() is not None:
        return Path(sys.executable)
    caller_jax = _caller_version("jax")
    jax_version = jax_version or caller_jax
    if jax_version is None:
        raise ReferenceEnvError("jax is not installed in this interpreter; pass jax_version explicitly")
    same_as_caller = jax_version == caller_jax
    jaxlib_version = (_caller_version("jaxlib") if same_as_caller else None) or jax_version
    accelerator = _mirrored_accelerator_packages() if same_as_caller else []
    wanted = _wanted_stamp(jax_version, jaxlib_version, accelerator)
    venv = VENV_DIR
    with _lock(venv):
        stamp = _read_stamp(venv)
        current = stamp is not None and {k: stamp.get(k) for k in wanted} == wanted
        if force or not current or not _venv_python(venv).exists():
            _build(venv, wanted)
    return _venv_python(venv)


def _clean_environment() -> dict[str, str]:
    """The caller's environment minus anything that would put our project's packages on the runner's path
    (with ``IMPULSE_REFERENCE_SITE``, the path is that folder alone)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    site = reference_site()
    if site is not None:
        env["PYTHONPATH"] = str(site)
    env["PYTHONUNBUFFERED"] = "1"
    # The runner shares the GPU with the process that called it, which may already hold most of its memory.
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    return env


def run_reference(args: list[str], timeout: float, script: Path = RUNNER) -> list[dict[str, Any]]:
    """Run ``script ARGS`` (by default ``_reference_runner.py``; any script beside it that follows the same
    JSON-lines convention) in the reference venv and return its JSON-lines stdout as dicts.

    The runner's stderr (progress) is forwarded live to ours. Raises ReferenceEnvError on a non-zero exit or a
    timeout, with the tail of its stderr.
    """
    python = ensure_reference_env()
    # -I keeps the runner's interpreter from seeing anything of ours; in site mode only PYTHONPATH must stay.
    isolation = "-s" if reference_site() is not None else "-I"
    command = [str(python), isolation, str(script), *args]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        env=_clean_environment(),  # the caller's working directory: relative paths mean the same on both sides
    )
    assert process.stdout is not None and process.stderr is not None
    err_tail: collections.deque[str] = collections.deque(maxlen=PIP_TAIL_LINES)
    out_lines: list[str] = []

    def forward_stderr() -> None:
        for line in process.stderr:  # type: ignore[union-attr]
            err_tail.append(line.rstrip("\n"))
            print(line, end="", file=sys.stderr, flush=True)

    def collect_stdout() -> None:
        out_lines.extend(process.stdout)  # type: ignore[arg-type]

    readers = [threading.Thread(target=forward_stderr, daemon=True), threading.Thread(target=collect_stdout,
                                                                                      daemon=True)]
    for reader in readers:
        reader.start()
    try:
        returncode = process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise ReferenceEnvError(
            f"reference runner timed out after {timeout:.0f}s: {shlex.join(command)}\n" + "\n".join(err_tail)
        ) from None
    finally:
        for reader in readers:
            reader.join(timeout=10)
    if returncode != 0:
        raise ReferenceEnvError(
            f"reference runner failed (exit {returncode}): {shlex.join(command)}\n" + "\n".join(err_tail)
        )
    records = []
    for raw in out_lines:
        line = raw.strip()
        if line.startswith("{"):
            records.append(json.loads(line))
    return records


def main(argv: list[str] | None = None) -> None:
    """Script entry: with no arguments build/check the venv and print its python; otherwise pass the arguments
    to the reference runner and print its JSON lines."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        if not argv or argv == ["--force"]:
            print(ensure_reference_env(force=bool(argv)))
            return
        for record in run_reference(argv, timeout=3600):
            print(json.dumps(record), flush=True)
    except ReferenceEnvError as error:
        raise SystemExit(f"error: {error}") from None


if __name__ == "__main__":
    main()
