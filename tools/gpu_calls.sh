#!/bin/bash
# The GPU benchmarks in two calls that fit a lent machine's 15 minutes of device time (docs/gpu.md), run there
# from the repository root after `python -m tools.gpu_bundle` here:
#
#     bash tools/gpu_calls.sh 1     # carry [".device"], timeout_s 560: engine, env, S training  (~7 min)
#     bash tools/gpu_calls.sh 2     # at once, on the warm machine, timeout_s 320: distributed, fused kernel
#
# Each benchmark has its own time limit, so a slow one loses its own last lines and not the others'. JSON lines go
# to $OUT/gpu.jsonl (call N's start line says "call": N, so `impulse bench gpu_table` reads both calls as one run),
# progress and errors to $OUT/log. The sizes are what the first lent H200 (2026-11-26) finished inside the limits.
set -u
part=${1:?usage: tools/gpu_calls.sh 1|2}
mkdir -p "$OUT"
exec 2> >(tee -a "$OUT/log" >&2)
started=$(date +%s)
[ -d /tmp/site/zenoh ] || python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site \
    .device/wheels/*.whl >&2 || echo "gpu_calls: installing the bundle's wheels failed" >&2
# A bundle built by an older checkout can lack a package that ours needs now (tensorboardX did, once, and a run
# failed after its first compile): say so at once, before any device time goes into a benchmark.
PYTHONPATH=/tmp/site python3 -c "import zenoh, tomli_w, tensorboardX" >&2 \
    || { echo "gpu_calls: the bundle lacks a package above; rebuild it with python -m tools.gpu_bundle" >&2; exit 2; }
# Preallocation off: the reference systems run in a child process beside ours, which would otherwise hold 75% of
# the GPU's memory while they run.
export PYTHONPATH=/tmp/site IMPULSE_REFERENCE_SITE=/tmp/site IMPULSE_KINETIX_LEVELS=$PWD/.device/kinetix-levels \
    PYTHONUNBUFFERED=1 JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache XLA_PYTHON_CLIENT_PREALLOCATE=false
results=$OUT/gpu.jsonl
printf '{"bench_gpu": "start", "utc": "%s", "commit": "%s", "call": %s}\n' "$(date -u +%Y-%m-%dT%H:%M:%SZ)" \
    "$(git rev-parse --short HEAD 2>/dev/null || cat .device/commit 2>/dev/null)" "$part" >> "$results"
bench() {
    local limit=$1; shift
    echo "== [$(( $(date +%s) - started ))s] $*" >&2
    timeout --kill-after=10 "$limit" python3 -m "impulse.benchmarks.$@" >> "$results"
    echo "== exit $? after $(( $(date +%s) - started ))s" >&2
}
if [ "$part" = 1 ]; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv >&2
    bench 240 engine --num-envs 32768
    bench 130 env --num-envs 32768 --sizes s,l
    bench 120 train --sizes s --kinetix-settings
else
    bench 185 distributed --parts runs --size s --kinetix-settings --set network.width=128 --set network.depth=5 \
        --set bus.shm_pool_mib=512 --actors 1 2 --updates 12 --skip 3 --no-fused-after --timeout 150
    bench 110 kernel_check --sizes s --random 20 --steps 60 --no-shared
fi
echo "== done after $(( $(date +%s) - started ))s" >&2
