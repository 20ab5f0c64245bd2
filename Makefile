# Two commands for a fresh machine: `make run` (the main job) and `make test` (lint, then the test suite as three
# parallel streams, see tests/conftest.py).
# Both create .venv with python3 (3.11 or 3.12) and install the project into it; the install is redone only
# when pyproject.toml changes (the stamp file below), so later runs start at once.

PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.impulse-installed

.PHONY: run test venv bench-gpu

run: $(STAMP)
	$(VENV)/bin/impulse launch --config configs/quick-launch.toml

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pytest -n 3 --dist loadgroup --durations=20

venv: $(STAMP)

# `make bench-gpu`: every GPU benchmark at GPU sizes in one go, against Jax2D (engine) and Kinetix (env) measured in
# the same run, on a machine whose JAX sees a GPU. Sized for under 25 minutes on one H100 in the usual case (the
# limits add up to 27.5): each benchmark has a time limit (GPU_LIMIT seconds), so a slow one loses its last lines
# rather than the others. The fused physics kernel (env.physics_backend = "pallas") is timed beside the XLA step
# (engine, S training) and checked against it (kernel_check). The profile (benchmarks/profile.py) splits an S
# training iteration into its parts. JSON lines are appended to GPU_RESULTS (one start line per run names the
# commit), progress goes to the terminal. Building the reference venv (benchmarks/reference_env.py, needs the
# package index) is not counted; without it, engine and env run alone.
# Distributed: train.py's network and settings (2,048 envs x 64 steps, entity network 128 x 5, all S levels); a
# 2,048 x 64 batch is a ~157 MB frame, so the shared-memory pool is raised to 512 MiB (>= 2x, see bus/session.py).
# BENCH_PYTHON: the interpreter that runs them; on a lent GPU machine, whose own Python holds JAX with CUDA and
# which cannot reach a package index, `make bench-gpu BENCH_PYTHON=python3` skips the venv (docs/gpu.md).
GPU_RESULTS := benchmarks/results/gpu-$(shell date +%Y-%m-%d).jsonl
BENCH_PYTHON ?= $(VENV)/bin/python
GPU_LIMIT = timeout --kill-after=30 $(1) $(BENCH_PYTHON) -m

# Preallocation off: the reference systems run in a child process beside ours (see tools/gpu_calls.sh).
bench-gpu: export XLA_PYTHON_CLIENT_PREALLOCATE = false
bench-gpu: $(if $(filter $(VENV)/bin/python,$(BENCH_PYTHON)),$(STAMP))
	@$(BENCH_PYTHON) -c "import sys, jax; b = jax.default_backend(); sys.exit(b != 'gpu' and f'bench-gpu: JAX backend is {b}, not gpu')"
	mkdir -p benchmarks/results
	printf '{"bench_gpu": "start", "utc": "%s", "commit": "%s"}\n' "$$(date -u +%Y-%m-%dT%H:%M:%SZ)" \
		"$$(git rev-parse --short HEAD 2>/dev/null)" >> $(GPU_RESULTS)
	status=0; ref=; \
	$(BENCH_PYTHON) benchmarks/reference_env.py > /dev/null \
		|| { echo "bench-gpu: no reference venv: engine and env run without Jax2D and Kinetix" >&2; ref=--no-reference; status=1; }; \
	$(call GPU_LIMIT,420) impulse.benchmarks.engine --num-envs 1,32768 --backend xla,pallas $$ref >> $(GPU_RESULTS) || status=1; \
	$(call GPU_LIMIT,180) impulse.benchmarks.kernel_check --random 1000 --steps 120 >> $(GPU_RESULTS) || status=1; \
	$(call GPU_LIMIT,180) impulse.benchmarks.env --num-envs 32768 $$ref >> $(GPU_RESULTS) || status=1; \
	$(call GPU_LIMIT,300) impulse.benchmarks.train --sizes s m l --kinetix-settings >> $(GPU_RESULTS) || status=1; \
	$(call GPU_LIMIT,120) impulse.benchmarks.train --sizes s --kinetix-settings --physics-backend pallas >> $(GPU_RESULTS) || status=1; \
	$(call GPU_LIMIT,120) impulse.benchmarks.profile --sizes s --kinetix-settings >> $(GPU_RESULTS) || status=1; \
	$(call GPU_LIMIT,330) impulse.benchmarks.distributed --parts runs costs --size s --kinetix-settings \
		--set network.width=128 --set network.depth=5 --set bus.shm_pool_mib=512 \
		--actors 1 2 4 --updates 20 --no-fused-after --timeout 200 >> $(GPU_RESULTS) || status=1; \
	echo "bench-gpu: JSON lines appended to $(GPU_RESULTS)"; exit $$status

$(STAMP): pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q -e '.[dev]'
	touch $(STAMP)
