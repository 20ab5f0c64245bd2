"""The fused solver kernel's size (`SolverOptions.backend="pallas"`, engine/physics/solver_kernel.py): the CPU's proxy
for how long Triton takes to compile it.

A GPU compile of the kernel cannot be timed without a GPU, but what the compilers are handed can be measured here.
For each size, on a vmapped batch of `--scenes` empty scenes (the program depends on the slot counts only), one JSON
line with:

- `kernel_eqns`: the equations of the kernel body, the jaxpr inside the `pallas_call`, counted recursively
  (loop bodies once each, as the compiler sees them); `step_eqns`: the same for the whole jaxpr of the step;
- `interpret_hlo_chars` / `interpret_hlo_ops`: the StableHLO of `jit(vmap(step))` with `backend="pallas_interpret"`
  (the kernel through Pallas's interpreter, which is how it runs on a CPU), its text size and its op count;
  `interpret_lower_s` / `interpret_compile_s`: the time to lower and to compile that step with XLA on this CPU;
  `xla_hlo_ops` / `xla_compile_s`: the same for the step with `backend="xla"`, the floor that the rest of the step
  (detection, integration, ...) sets;
- `triton_ir_bytes`: the Triton module (MLIR bytecode) that the step lowered for CUDA with `backend="pallas"` hands
  to Triton's compiler, and `cuda_lower_s`, the time to lower that step (Pallas's Triton lowering runs on any
  machine; Triton's own compile of that module, the slow part on the GPU, does not run here).

    impulse bench kernel_size                           # S, M, L
    impulse bench kernel_size --sizes s --no-compile    # sizes and lowering only, no XLA compile
"""

from __future__ import annotations

import argparse
import re
import time
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
from jax.extend import core as jex_core

from impulse.benchmarks._harness import emit, environment, progress
from impulse.engine.physics.building import empty_scene
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SceneSizes, size_preset
from impulse.engine.physics.state import SimState
from impulse.engine.physics.step import step

OP_LINE = re.compile(r'^\s*(?:%[^=]*=\s*)?"?[a-z_]+\.[a-z_.]+', re.MULTILINE)
"""A line of MLIR text that holds an operation (`%x = stablehlo.add ...`, `"stablehlo.case"(...)`, `func.return`)."""


def sub_jaxprs(value: object) -> Iterator[jex_core.Jaxpr]:
    """The jaxprs held in one equation parameter (a jaxpr, a closed jaxpr, or a tuple of them, as cond's
    branches)."""
    if isinstance(value, jex_core.ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, jex_core.Jaxpr):
        yield value
    elif isinstance(value, tuple | list):
        for item in value:
            yield from sub_jaxprs(item)


def count_equations(jaxpr: jex_core.Jaxpr) -> int:
    """Equations of `jaxpr` and of every jaxpr nested in them (loop and branch bodies, the kernel body)."""
    return sum(1 + sum(count_equations(sub) for value in eqn.params.values() for sub in sub_jaxprs(value))
               for eqn in jaxpr.eqns)


def kernel_jaxprs(jaxpr: jex_core.Jaxpr) -> Iterator[jex_core.Jaxpr]:
    """The kernel bodies of every `pallas_call` in `jaxpr`, at any depth."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "pallas_call":
            yield eqn.params["jaxpr"]
            continue
        for value in eqn.params.values():
            for sub in sub_jaxprs(value):
                yield from kernel_jaxprs(sub)


def triton_ir_bytes(lowered: jax.stages.Lowered) -> int:
    """Bytes of the Triton module(s) that a step lowered for CUDA carries in its Triton custom calls."""
    total = 0

    def visit(op) -> None:
        nonlocal total
        for region in op.regions:
            for block in region.blocks:
                for inner in block.operations:
                    if inner.operation.name == "stablehlo.custom_call":
                        attributes = inner.operation.attributes
                        target = str(attributes["call_target_name"])
                        if "triton" in target and "mhlo.backend_config" in attributes:
                            total += len(attributes["mhlo.backend_config"]["ir"].value_bytes)
                    visit(inner.operation)

    visit(lowered.compiler_ir("stablehlo").operation)
    return total


def abstract_batch(sizes: SceneSizes, scenes: int) -> tuple[SimState, jax.ShapeDtypeStruct]:
    """Shapes of a batch of `scenes` scenes and their actions: the step's program depends on nothing else."""
    one = jax.eval_shape(lambda: empty_scene(sizes))
    batch = jax.tree.map(lambda leaf: jax.ShapeDtypeStruct((scenes,) + leaf.shape, leaf.dtype), one)
    return batch, jax.ShapeDtypeStruct((scenes, sizes.num_joints + sizes.num_thrusters), jnp.float32)


def batched_step(sizes: SceneSizes, backend: str) -> Callable:
    """jit(vmap(step)) of empty-parameter scenes with the given solver backend (the rest of the options default)."""
    params, options = SimParams(), SolverOptions(backend=backend)
    return jax.jit(jax.vmap(lambda s, a: step(s, params, a, sizes, options)[0]))


def equations(step_jaxpr: jex_core.Jaxpr) -> tuple[int, int]:
    """(kernel body, whole step): equations of a traced step with the kernel, counted recursively."""
    kernels = list(kernel_jaxprs(step_jaxpr))
    if len(kernels) != 1:
        raise RuntimeError(f"expected one pallas_call in the step, found {len(kernels)}")
    return count_equations(kernels[0]), count_equations(step_jaxpr)


def kernel_equations(sizes: SceneSizes, scenes: int = 16) -> int:
    """Equations of the kernel body for scenes of `sizes` (traced only: nothing is lowered or compiled)."""
    traced = batched_step(sizes, "pallas_interpret").trace(*abstract_batch(sizes, scenes))
    return equations(traced.jaxpr.jaxpr)[0]


def measure(sizes: SceneSizes, scenes: int, compile_interpreted: bool) -> dict:
    """The figures of the module docstring for one size."""
    batch, actions = abstract_batch(sizes, scenes)
    traced = batched_step(sizes, "pallas_interpret").trace(batch, actions)
    kernel_eqns, step_eqns = equations(traced.jaxpr.jaxpr)
    started = time.perf_counter()
    lowered = traced.lower()
    lower_s = time.perf_counter() - started
    text = lowered.as_text()
    record = {
        "kernel_eqns": kernel_eqns,
        "step_eqns": step_eqns,
        "interpret_hlo_chars": len(text),
        "interpret_hlo_ops": len(OP_LINE.findall(text)),
        "interpret_lower_s": round(lower_s, 2),
    }
    if compile_interpreted:
        started = time.perf_counter()
        lowered.compile()
        record["interpret_compile_s"] = round(time.perf_counter() - started, 2)
        lowered_xla = batched_step(sizes, "xla").trace(batch, actions).lower()
        record["xla_hlo_ops"] = len(OP_LINE.findall(lowered_xla.as_text()))
        started = time.perf_counter()
        lowered_xla.compile()
        record["xla_compile_s"] = round(time.perf_counter() - started, 2)
    started = time.perf_counter()
    for_cuda = batched_step(sizes, "pallas").trace(batch, actions).lower(lowering_platforms=("cuda",))
    record["cuda_lower_s"] = round(time.perf_counter() - started, 2)
    record["triton_ir_bytes"] = triton_ir_bytes(for_cuda)
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench kernel_size", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="s,m,l", help="comma-separated sizes among s,m,l")
    parser.add_argument("--scenes", type=int, default=16, help="scenes in the vmapped batch (one block)")
    parser.add_argument("--no-compile", action="store_true", help="skip the XLA compiles (interpreted and XLA step)")
    args = parser.parse_args(argv)
    info = environment()
    for name in args.sizes.split(","):
        progress(f"kernel_size: size {name} ...")
        record = measure(size_preset(name), args.scenes, not args.no_compile)
        emit({"bench": "kernel_size", "size": name, "scenes": args.scenes, **record, **info})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
