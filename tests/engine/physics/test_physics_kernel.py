"""The fused solver kernel (`SolverOptions.backend="pallas"`, engine/physics/solver_kernel.py) against the XLA step.

Its numbers are checked through Pallas's interpreter on CPU (`backend="pallas_interpret"`, on a vmapped batch);
that it is a kernel Triton accepts, batched and for one scene, is checked by lowering the step for a CUDA GPU,
which needs no GPU; that it stays small (rolled: its loops are the kernel's, so its body does not grow with the
scene) by counting its equations at two sizes. The full check on every shared level and 1,000 random levels per
size is `impulse bench kernel_check` on a GPU (benchmarks/RESULTS.md).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.benchmarks._harness import LEVELS_DIR
from impulse.benchmarks.kernel_check import compare, shared_levels
from impulse.benchmarks.kernel_size import kernel_equations
from impulse.engine.env.config import EnvConfig
from impulse.engine.env.spec import env_from_config
from impulse.engine.physics import SIZE_L, SIZE_S, SolverOptions, step
from tests.support.level_samples import host_levels

# Measured (2026-12-02) after 120 steps: 1.9e-5 m over the NUM_SCENES scenes (the unrolled kernel before it: 5.0e-6 m),
# 1.1e-5 m on the 10 shared S levels batched alone (unrolled: 1.3e-5 m). Float rounding, the same arithmetic evaluated
# in another order; a wrong term in a visit parts them by millimetres at once.
TOLERANCE_M = 1e-4

# The kernel body, in jaxpr equations: 500 at every size on 2026-12-02 (one joint visit and one contact visit), where
# the unrolled kernel had 2,762 at S and 25,441 at L and did not compile on a GPU within 240 s.
MAX_KERNEL_EQUATIONS = 1000


# Scenes compared: the shared S levels topped up with random ones. test_generator's NaN check steps batches of this
# many random S levels for as many steps through the same `trajectories`, so the XLA side compiles once for both.
NUM_SCENES = 16
NUM_STEPS = 120


@functools.cache
def _levels_of_size_s():
    """The shared S levels and random ones up to NUM_SCENES, from the 4,000-level batch the level tests draw (one
    compile of the generator, and one sample, for all of them)."""
    if not (LEVELS_DIR / "s").is_dir():
        pytest.skip(f"Kinetix level files not found at {LEVELS_DIR.resolve()} (the shared folder beside the checkout)")
    shared, params, sizes = shared_levels("s")
    count = NUM_SCENES - shared.bodies.position.shape[0]
    assert count > 0, "more shared S levels than NUM_SCENES"
    randoms = jax.tree.map(lambda x: x[:count], host_levels("s").state)
    # Host arrays, so the slicing below is numpy's rather than one small compiled program per leaf.
    return jax.tree.map(lambda a, b: np.concatenate([np.asarray(a), b]), shared, randoms), params, sizes


def test_kernel_follows_the_xla_step_for_120_steps_on_shared_and_random_levels() -> None:
    states, params, sizes = _levels_of_size_s()
    result = compare(states, params, sizes, num_steps=NUM_STEPS)
    assert result["kernel_backend"] == "pallas_interpret"
    assert result["finite"]
    assert result["max_apart_any_step_m"] <= TOLERANCE_M, result


def test_the_step_lowers_to_one_triton_kernel_for_cuda_batched_or_not_and_to_plain_xla_for_cpu() -> None:
    states, params, sizes = _levels_of_size_s()
    options = SolverOptions(backend="pallas")
    scenes = jax.tree.map(lambda x: x[:4], states)
    actions = jnp.zeros((4, sizes.num_joints + sizes.num_thrusters))
    batched = jax.jit(jax.vmap(lambda s, a: step(s, params, a, sizes, options)[0]))
    one = jax.jit(lambda s, a: step(s, params, a, sizes, options)[0])
    lowered = {
        "batched for cuda": batched.trace(scenes, actions).lower(lowering_platforms=("cuda",)).as_text(),
        "one scene for cuda": one.trace(jax.tree.map(lambda x: x[0], scenes), actions[0]).lower(
            lowering_platforms=("cuda",)).as_text(),
        "batched for cpu": batched.trace(scenes, actions).lower(lowering_platforms=("cpu",)).as_text(),
    }
    assert lowered["batched for cuda"].count("__gpu$xla.gpu.triton") == 1
    assert lowered["one scene for cuda"].count("__gpu$xla.gpu.triton") == 1
    assert "triton" not in lowered["batched for cpu"]


def test_the_kernel_is_rolled_so_its_body_is_as_small_for_l_as_for_s() -> None:
    at_s, at_l = kernel_equations(SIZE_S), kernel_equations(SIZE_L)
    assert at_s == at_l, (at_s, at_l)
    assert at_s <= MAX_KERNEL_EQUATIONS


def test_backend_setting_is_checked_and_reaches_the_solver_options() -> None:
    with pytest.raises(ValueError, match="unknown physics backend"):
        SolverOptions(backend="cuda")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="phased schedule only"):
        SolverOptions(backend="pallas", schedule="jax2d")
    spec, _ = env_from_config(EnvConfig(physics_backend="pallas"))
    assert spec.solver.backend == "pallas"
    assert env_from_config(EnvConfig())[0].solver.backend == "xla"
