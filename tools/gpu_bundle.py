"""Pack what `make bench-gpu` needs on a lent GPU machine that cannot reach a package index: `.device/`.

A lent machine (docs/gpu.md) has Python 3.12 with JAX (CUDA), flax, optax, orbax, numpy and pillow, but not the
rest of our dependencies, nor Jax2D and Kinetix, nor Kinetix's level files (the shared folder beside the checkout
does not travel). This script, run here where pip reaches the index, downloads the missing pieces as wheels for
that machine and copies the levels:

    python -m tools.gpu_bundle          # writes .device/wheels and .device/kinetix-levels, prints the command

The bundle must stay under the 64 MiB a call may carry, working tree included, so only what the machine lacks is
fetched (`DEVICE_HAS`, read from the machine's package list) and rerun-sdk (170 MB) is left out: runs there have
monitoring off, which imports no rerun (docs/gpu.md).

Stdlib only: it runs before anything is installed.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BUNDLE = REPO / ".device"
CARRY_LIMIT_BYTES = 64 * 2**20
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux1_x86_64")
PYTHON_VERSION = "3.12"

# Ours, beyond what the machine has (rerun-sdk is left out: see the module docstring).
OURS = ["eclipse-zenoh>=1.0", "tomli-w>=1.0", "tensorboardX>=2.6"]
# What Jax2D's engine and Kinetix's environment import (`kinetix.environment` and `kinetix.util`, whose package
# imports its networks, configs and data loader), then the two packages installed without their stale pins.
# benchmarks/reference_env.py's list also has zarr and numcodecs (Kinetix's offline dataset), which only CPU
# comparisons use and which would push the bundle past the carry limit (docs/gpu.md).
REFERENCE_DEPENDENCIES = ["gymnax", "jaxgl", "distrax", "omegaconf", "grain", "wandb"]
REFERENCE_NO_DEPS = ["jax2d==1.0.2", "kinetix-env==3.0.2"]

# The lent machines' Python packages, as listed in the device tool's notes (2026-11-17); wheels of these are not
# carried, so the machine's own versions (its JAX above all) are the ones that run.
DEVICE_HAS = frozenset("""
absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch build certifi
charset-normalizer chex click cloudpickle cmake colorama contourpy coverage cuda-bindings cuda-core cuda-pathfinder
cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops equinox etils execnet filelock flatbuffers flax fonttools
formulaic frozenlist fsspec gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna
imageio iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver
lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml markdown markdown-it-py markupsafe
matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack multidict multipledispatch mypy-extensions nanobind narwhals
networkx ninja numba numba-cuda numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime
nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13
nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript
opencv-python-headless optax opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy
peft pillow pip pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock pytest-timeout pytest-xdist
python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu safetensors scikit-build-core scikit-image
scikit-learn scipy seaborn sentencepiece sentence-transformers setuptools shellingham simplejson six
sortedcontainers statsmodels sympy tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile
tiktoken timm tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm
transformers treescope triton typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel
wrapt xarray xxhash yarl zipp
""".split())

DEVICE_COMMAND = (
    "python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .device/wheels/*.whl && "
    "export PYTHONPATH=/tmp/site IMPULSE_REFERENCE_SITE=/tmp/site "
    "IMPULSE_KINETIX_LEVELS=$PWD/.device/kinetix-levels PYTHONUNBUFFERED=1 && "
    "make bench-gpu BENCH_PYTHON=python3; cp benchmarks/results/gpu-*.jsonl $OUT/"
)


def distribution_name(wheel: Path) -> str:
    """A wheel file's project name, normalised as pip lists it (lower case, dashes)."""
    return re.split(r"-\d", wheel.name, maxsplit=1)[0].lower().replace("_", "-")


def download(requirements: list[str], into: Path, with_deps: bool) -> None:
    command = [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check", "--only-binary=:all:",
               "--python-version", PYTHON_VERSION, "--implementation", "cp", "-d", str(into)]
    command += [arg for platform in PLATFORMS for arg in ("--platform", platform)]
    if not with_deps:
        command.append("--no-deps")
    result = subprocess.run([*command, *requirements], text=True, capture_output=True, check=False)
    if result.returncode != 0:
        lines = [line for line in result.stderr.splitlines() if "Location 'file:" not in line]
        raise SystemExit("pip download failed:\n" + "\n".join(lines[-20:]))


def tree_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.gpu_bundle", description=__doc__.split("\n")[0])
    parser.add_argument("--levels", type=Path, default=REPO.parent / "shared" / "kinetix-levels",
                        help="Kinetix's level folder (holding s/, m/ and l/)")
    parser.add_argument("--no-reference", action="store_true", help="leave Jax2D and Kinetix out")
    args = parser.parse_args(argv)
    if not (args.levels / "s").is_dir():
        raise SystemExit(f"no Kinetix levels at {args.levels} (want a folder holding s/, m/ and l/)")
    wheels = BUNDLE / "wheels"
    shutil.rmtree(BUNDLE, ignore_errors=True)
    wheels.mkdir(parents=True)
    print(f"downloading wheels for Python {PYTHON_VERSION} into {wheels} ...", file=sys.stderr)
    download(OURS + ([] if args.no_reference else REFERENCE_DEPENDENCIES), wheels, with_deps=True)
    if not args.no_reference:
        download(REFERENCE_NO_DEPS, wheels, with_deps=False)
    for wheel in sorted(wheels.glob("*.whl")):
        if distribution_name(wheel) in DEVICE_HAS:
            wheel.unlink()
    shutil.copytree(args.levels, BUNDLE / "kinetix-levels", ignore=shutil.ignore_patterns("*.py", "__pycache__"))
    # The lent machine gets the working tree without .git: the commit its results name travels in a file.
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout
    (BUNDLE / "commit").write_text(commit.strip() + "\n")
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    tree = sum((REPO / name).stat().st_size for name in tracked.decode().split("\0") if name and
               (REPO / name).is_file())
    total = tree_bytes(BUNDLE) + tree
    for wheel in sorted(wheels.glob("*.whl")):
        print(f"  {wheel.stat().st_size / 2**20:6.2f} MiB  {wheel.name}", file=sys.stderr)
    print(f"bundle {tree_bytes(BUNDLE) / 2**20:.1f} MiB + tracked tree {tree / 2**20:.1f} MiB = "
          f"{total / 2**20:.1f} MiB of the {CARRY_LIMIT_BYTES / 2**20:.0f} MiB a call carries", file=sys.stderr)
    if total > CARRY_LIMIT_BYTES:
        print("over the limit: try --no-reference", file=sys.stderr)
        return 1
    print("device call: carry [\".device\"], command:", file=sys.stderr)
    print(DEVICE_COMMAND)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
