#!/bin/bash
# The GPU benchmarks in two calls that fit a lent machine's 15 minutes of device time (docs/gpu.md), run there
# from the repository root after `python -m tools.gpu_bundle` here:
#
#     bash tools/gpu_calls.sh 1     # carry [".device"], timeout_s 560: engine, env, S training  (~7 min)
#     bash tools/gpu_calls.sh 2     # at once, on the warm machine, timeout_s 320: distributed, fused kernel
#     bash tools/gpu_calls.sh general   # carry [".device"], timeout_s 590: train the general S agent (issue 26)
#     bash tools/gpu_calls.sh learning  # carry [".device"], timeout_s 590: distributed against fused (issue 26)
#
# `learning` runs `impulse bench learning` at Kinetix's settings (2,048 envs x 64 steps, 8 epochs x 32 minibatches,
# lr 1e-4, batch-scored SFL, the entity transformer; LEARNING_NETWORK=entity for the 221,521-parameter network),
# fused then distributed, each for LEARNING_STEPS env steps or 210 s, whichever comes first: a run still training
# at 210 s is interrupted, checkpoints and is scored, and its curve says how far it got.
# `general` trains GENERAL_CONFIG (default configs/general-s-gpu.toml; from the policy of run GENERAL_INIT when set,
# e.g. pretrained/general-s) for GENERAL_SECONDS (default 390; SIGINT then checkpoints), exports
# the last checkpoint to $OUT/general-s and scores it on Kinetix S, our hand-made S and Kinetix M. The run's
# metrics.jsonl and config.toml come back beside it; the export's checkpoint lies deeper than the 16 folders the
# tool returns, so a next call on the warm machine tars /tmp/general-s into $OUT (docs/gpu.md).
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
elif [ "$part" = general ]; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv >&2
    run=/tmp/general-s
    echo "== [$(( $(date +%s) - started ))s] training for ${GENERAL_SECONDS:-390} s" >&2
    timeout -s INT --kill-after=40 "${GENERAL_SECONDS:-390}" python3 -m impulse.deploy.cli train \
        --config "${GENERAL_CONFIG:-configs/general-s-gpu.toml}" ${GENERAL_INIT:+--init-from "$GENERAL_INIT"} \
        run_dir=$run >&2
    echo "== training exit $? after $(( $(date +%s) - started ))s" >&2
    cp $run/config.toml $run/metrics.jsonl "$OUT/" 2>/dev/null
    python3 -m impulse.deploy.cli export --checkpoint $run --out /tmp/general-s-export \
        --note trained_on="$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1)" >&2 \
        && tar -czf "$OUT/general-s.tgz" -C /tmp general-s-export
    for set in kinetix:s handmade; do
        echo "== [$(( $(date +%s) - started ))s] eval $set" >&2
        timeout 60 python3 -m impulse.deploy.cli eval --checkpoint /tmp/general-s-export --levels $set --attempts 20 \
            --seed 0 --json "$OUT/eval-${set#*:}.json" >&2
    done
    echo "== [$(( $(date +%s) - started ))s] eval kinetix:m" >&2
    timeout 70 python3 -m impulse.deploy.cli eval --checkpoint /tmp/general-s-export --levels kinetix:m --attempts 20 \
        --seed 0 --json "$OUT/eval-m.json" env.size=m >&2
elif [ "$part" = learning ]; then
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv >&2
    # shellcheck disable=SC2086 # SEEDS is a list of words
    bench 540 learning --seeds ${SEEDS:-0} --env-steps "${LEARNING_STEPS:-13107200}" --eval-every 25 --attempts 20 \
        --timeout 210 --plot "$OUT/learning.png" --set network.kind="${LEARNING_NETWORK:-transformer}" \
        --set network.width=128 --set network.depth=5 --set ppo.num_envs=2048 \
        --set ppo.num_minibatches=32 --set ppo.update_epochs=8 --set ppo.learning_rate=1e-4 \
        --set curriculum.sfl_scoring=batch --set curriculum.sfl_candidates=8192 --set curriculum.sfl_attempts=4 \
        --set curriculum.sfl_refresh_updates=32 --set curriculum.buffer_size=1024 --set bus.shm_pool_mib=512
else
    bench 185 distributed --parts runs --size s --kinetix-settings --set network.width=128 --set network.depth=5 \
        --set bus.shm_pool_mib=512 --actors 1 2 --updates 12 --skip 3 --no-fused-after --timeout 150
    bench 110 kernel_check --sizes s --random 20 --steps 60 --no-shared
fi
echo "== done after $(( $(date +%s) - started ))s" >&2
