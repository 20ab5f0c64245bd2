"""Stage 5 of the step, the solver iterations, as one Pallas kernel per block of scenes (`backend="pallas"`).

Why: on a GPU the XLA step runs every joint visit and every contact phase of every iteration as its own chain of
small kernels that read and write the bodies in global memory; a Kinetix scene is 1-2 KB, so the step is bound
by launches and memory traffic (docs/engine.md). Here a block of scenes (one per lane) loads its bodies, joint
accumulators and contact impulses once, runs all `options.iterations` sweeps with them held as values, and
stores them once. The per-contact constants stay in the block's input and are read where they are used.

What it computes is `step.iterate_phased`, visit for visit: per iteration the joints in slot order
(joint_solver.solve_joint), then the contacts phase by phase (contact_solver.solve_phase; a phase's contacts
share no body, so visiting them one after another gives what solving them side by side gives). The formulas are
those two functions' written over lanes instead of slots; tests/engine/physics/test_physics_kernel.py holds the
kernel to the XLA schedule on levels and random scenes.

Layout (lanes.py): every body, joint and contact slot is a row, indices are unrolled at trace time, a joint's
bodies (scene data) are picked by one-hot weights over the bodies as in joint_solver. The kernel is written for
Triton (`jax.experimental.pallas.triton`); on other platforms `step` runs the XLA schedule instead, and
`interpret=True` runs the kernel through Pallas's interpreter anywhere (for tests).

The kernel works on a batch of scenes, the step on one: `iterate_kernel` is a `custom_vmap`, whose batching
rule hands the whole vmapped batch to the kernel with scenes on lanes; unbatched it runs one scene in one block.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from impulse.engine.physics.contact_solver import ContactRows
from impulse.engine.physics.context import Impulses, StepContext
from impulse.engine.physics.joint_solver import JointSolverState
from impulse.engine.physics.lanes import Row, RowLayout, Vector, flatten, vectors
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.params import CARRIED_IMPULSE_CAP
from impulse.engine.physics.sizes import SceneSizes
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pallas_triton

Array = jax.Array

MAX_LANES = 128
"""Scenes per block: one per thread of four warps."""

SOLVER_PARAMS = (
    "joint_stiffness",
    "baumgarte_coefficient_joints_v",
    "baumgarte_coefficient_joints_p",
    "baumgarte_coefficient_fjoint_av",
    "baumgarte_coefficient_rjoint_limit_av",
    "clip_velocity",
    "clip_angular_velocity",
)
CONTACT_FIELDS = ContactRows._fields
VECTOR_CONTACT_FIELDS = ("normal", "tangent", "lever_a", "lever_b")
JOINT_SCALARS = ("inverse_mass_a", "inverse_mass_b", "inverse_inertia_a", "inverse_inertia_b", "relative_angle",
                 "enabled", "is_fixed_joint", "motor_has_joint_limits", "min_rotation", "max_rotation")


@functools.cache
def layouts(sizes: SceneSizes) -> tuple[RowLayout, RowLayout]:
    """(state, constants): what the iterations change, and what they only read."""
    n, j, k = sizes.num_bodies, sizes.num_joints, pair_tables(sizes).num_contacts
    state = RowLayout((
        ("position", 2 * n), ("velocity", 2 * n), ("angular_velocity", n),
        ("acc_impulse", 2 * j), ("acc_r_impulse", j), ("anchor", 2 * j),
        ("normal_impulse", k), ("tangent_impulse", k),
    ))
    contact = tuple((f"contact_{name}", (2 if name in VECTOR_CONTACT_FIELDS else 1) * k) for name in CONTACT_FIELDS)
    joint = (("joint_a", j), ("joint_b", j), ("joint_lever_a", 2 * j), ("joint_lever_b", 2 * j)) + tuple(
        (f"joint_{name}", j) for name in JOINT_SCALARS
    )
    constants = RowLayout(contact + joint + (("params", len(SOLVER_PARAMS)),))
    return state, constants


def iterate_kernel(
    start: JointSolverState, carried: Impulses, context: StepContext, interpret: bool = False
) -> tuple[JointSolverState, Impulses]:
    """`step.iterate_phased` for one scene (vmap it: batches run as blocks of scenes): the solved joint state and
    the accumulated contact impulses in slot order."""
    rows, jrows, joints, params = context.contact_rows, context.joint_rows, context.joints, context.params
    state_fields = {
        "position": start.position, "velocity": start.velocity, "angular_velocity": start.angular_velocity,
        "acc_impulse": start.acc_impulse, "acc_r_impulse": start.acc_r_impulse, "anchor": start.anchor,
        "normal_impulse": carried.normal, "tangent_impulse": carried.tangent,
    }
    constant_fields = {f"contact_{name}": value for name, value in zip(CONTACT_FIELDS, rows, strict=True)}
    constant_fields |= {
        "joint_a": joints.a_index, "joint_b": joints.b_index,
        "joint_lever_a": jrows.lever_a, "joint_lever_b": jrows.lever_b,
        "joint_is_fixed_joint": joints.is_fixed_joint, "joint_motor_has_joint_limits": joints.motor_has_joint_limits,
        "joint_min_rotation": joints.min_rotation, "joint_max_rotation": joints.max_rotation,
        "joint_inverse_mass_a": jrows.inverse_mass_a, "joint_inverse_mass_b": jrows.inverse_mass_b,
        "joint_inverse_inertia_a": jrows.inverse_inertia_a, "joint_inverse_inertia_b": jrows.inverse_inertia_b,
        "joint_relative_angle": jrows.relative_angle, "joint_enabled": jrows.enabled,
        "params": jnp.stack([jnp.asarray(getattr(params, name), jnp.float32) for name in SOLVER_PARAMS]),
    }
    constant_fields = {name: jnp.asarray(value, jnp.float32) for name, value in constant_fields.items()}
    solved = _batched_solver(context.sizes, context.options.iterations, interpret)(state_fields, constant_fields)
    joint_state = JointSolverState(
        position=solved["position"], velocity=solved["velocity"], angular_velocity=solved["angular_velocity"],
        acc_impulse=solved["acc_impulse"], acc_r_impulse=solved["acc_r_impulse"], anchor=solved["anchor"],
    )
    return joint_state, Impulses(solved["normal_impulse"], solved["tangent_impulse"])


@functools.cache
def _batched_solver(sizes: SceneSizes, iterations: int, interpret: bool) -> Callable[[dict, dict], dict]:
    """One scene's fields in, solved fields out; under vmap, the whole batch goes to the kernel at once."""
    run = functools.partial(run_blocks, sizes=sizes, iterations=iterations, interpret=interpret)

    @jax.custom_batching.custom_vmap
    def solve(state_fields: dict, constant_fields: dict) -> dict:
        one = jax.tree.map(lambda x: x[None], (state_fields, constant_fields))
        return jax.tree.map(lambda x: x[0], run(*one))

    @solve.def_vmap
    def solve_batch(axis_size: int, in_batched: Any, state_fields: dict, constant_fields: dict):
        def batched(value: Array, is_batched: bool) -> Array:
            return value if is_batched else jnp.broadcast_to(value, (axis_size,) + value.shape)

        fields = jax.tree.map(batched, (state_fields, constant_fields), tuple(in_batched))
        solved = run(*fields)
        return solved, jax.tree.map(lambda _: True, solved)

    return solve


def run_blocks(state_fields: dict, constant_fields: dict, sizes: SceneSizes, iterations: int, interpret: bool) -> dict:
    """The kernel over a batch of scenes (leading axis of every field), in blocks of up to MAX_LANES scenes."""
    state_layout, constant_layout = layouts(sizes)
    scenes = state_fields["position"].shape[0]
    shapes = {name: value.shape for name, value in state_fields.items()}
    lanes = min(MAX_LANES, max(16, 1 << (scenes - 1).bit_length()))
    padded = -(-scenes // lanes) * lanes

    def lanes_of(layout: RowLayout, fields: dict) -> Array:
        packed = layout.pack(fields)
        return jnp.pad(packed, ((0, 0), (0, padded - scenes)))

    state_in = lanes_of(state_layout, state_fields)
    constants = lanes_of(constant_layout, constant_fields)
    kernel = functools.partial(solver_kernel, sizes=sizes, iterations=iterations)
    block = functools.partial(pl.BlockSpec, index_map=lambda i: (0, i))
    state_out = pl.pallas_call(
        kernel,
        out_shape=jax.ShapeDtypeStruct(state_in.shape, jnp.float32),
        grid=(padded // lanes,),
        in_specs=[block((state_layout.num_rows, lanes)), block((constant_layout.num_rows, lanes))],
        out_specs=block((state_layout.num_rows, lanes)),
        compiler_params=pallas_triton.CompilerParams(num_warps=max(1, lanes // 32)),
        interpret=interpret,
    )(state_in, constants)
    solved = state_layout.unpack(state_out[:, :scenes])
    return {name: solved[name].reshape(shapes[name]) for name in shapes}


def solver_kernel(state_ref, constants_ref, out_ref, *, sizes: SceneSizes, iterations: int) -> None:
    """All `iterations` solver sweeps of one block of scenes (see the module docstring)."""
    state_layout, constant_layout = layouts(sizes)
    tables = pair_tables(sizes)

    def constant(name: str, index: int) -> Row:
        return constant_layout.row(constants_ref, name, index)

    def constant_vector(name: str, index: int) -> Vector:
        return constant(name, 2 * index), constant(name, 2 * index + 1)

    p = dict(zip(SOLVER_PARAMS, constant_layout.load(constants_ref)["params"], strict=True))
    rows = state_layout.load(state_ref)
    carry = (
        vectors(rows["position"]), vectors(rows["velocity"]), rows["angular_velocity"],
        vectors(rows["acc_impulse"]), rows["acc_r_impulse"], vectors(rows["anchor"]),
        rows["normal_impulse"], rows["tangent_impulse"],
    )

    def iteration(_, carry):
        position, velocity, spin, acc, acc_r, anchor, normal, tangent = (list(part) for part in carry)
        for j in range(sizes.num_joints):
            visit_joint(j, position, velocity, spin, acc, acc_r, anchor, constant, constant_vector, p)
        for phase in tables.phases:
            for k in phase.tolist():
                a, b = int(tables.contact_a[k]), int(tables.contact_b[k])
                velocity[a], spin[a], velocity[b], spin[b], normal[k], tangent[k] = visit_contact(
                    k, velocity[a], spin[a], velocity[b], spin[b], normal[k], tangent[k], constant, constant_vector
                )
        return position, velocity, spin, acc, acc_r, anchor, normal, tangent

    position, velocity, spin, acc, acc_r, anchor, normal, tangent = jax.lax.fori_loop(
        0, iterations, iteration, carry
    )
    state_layout.store(out_ref, {
        "position": flatten(position), "velocity": flatten(velocity), "angular_velocity": list(spin),
        "acc_impulse": flatten(acc), "acc_r_impulse": list(acc_r), "anchor": flatten(anchor),
        "normal_impulse": list(normal), "tangent_impulse": list(tangent),
    })


def _nonzero(x: Row) -> Row:
    return jnp.where(x == 0, 1.0, x)


def _cross(a: Vector, b: Vector) -> Row:
    return a[0] * b[1] - a[1] * b[0]


def _dot(a: Vector, b: Vector) -> Row:
    return a[0] * b[0] + a[1] * b[1]


def _spin_velocity(spin: Row, lever: Vector) -> Vector:
    """spin x lever: the velocity of a point at `lever` on a body spinning at `spin`."""
    return -spin * lever[1], spin * lever[0]


def _add(a: Vector, b: Vector) -> Vector:
    return a[0] + b[0], a[1] + b[1]


def _sub(a: Vector, b: Vector) -> Vector:
    return a[0] - b[0], a[1] - b[1]


def _scale(s: Row, v: Vector) -> Vector:
    return s * v[0], s * v[1]


def visit_contact(k: int, va: Vector, wa: Row, vb: Vector, wb: Row, normal_impulse: Row, tangent_impulse: Row,
                  constant: Callable, constant_vector: Callable) -> tuple[Vector, Row, Vector, Row, Row, Row]:
    """contact_solver.solve_phase for contact slot k on every lane: normal impulse, then friction."""
    n, t = constant_vector("contact_normal", k), constant_vector("contact_tangent", k)
    lever_a, lever_b = constant_vector("contact_lever_a", k), constant_vector("contact_lever_b", k)
    ima, imb = constant("contact_inverse_mass_a", k), constant("contact_inverse_mass_b", k)
    iia, iib = constant("contact_inverse_inertia_a", k), constant("contact_inverse_inertia_b", k)

    def relative_velocity() -> Vector:
        return _sub(_add(vb, _spin_velocity(wb, lever_b)), _add(va, _spin_velocity(wa, lever_a)))

    def apply(impulse: Vector) -> tuple[Vector, Row, Vector, Row]:
        return (
            _sub(va, _scale(ima, impulse)), wa - iia * _cross(lever_a, impulse),
            _add(vb, _scale(imb, impulse)), wb + iib * _cross(lever_b, impulse),
        )

    normal_speed = _dot(relative_velocity(), n)
    target = constant("contact_target_velocity", k)
    new_normal = jnp.maximum(normal_impulse + (target - normal_speed) * constant("contact_normal_mass", k), 0.0)
    va, wa, vb, wb = apply(_scale(new_normal - normal_impulse, n))

    tangent_speed = _dot(relative_velocity(), t)
    limit = constant("contact_friction", k) * new_normal
    new_tangent = jnp.clip(tangent_impulse - tangent_speed * constant("contact_tangent_mass", k), -limit, limit)
    va, wa, vb, wb = apply(_scale(new_tangent - tangent_impulse, t))
    return va, wa, vb, wb, new_normal, new_tangent


def visit_joint(j: int, position: list[Vector], velocity: list[Vector], spin: list[Row], acc: list[Vector],
                acc_r: list[Row], anchor: list[Vector], constant: Callable, constant_vector: Callable,
                p: dict[str, Row]) -> None:
    """joint_solver.solve_joint for joint j on every lane, updating the lists in place. The joint's bodies are
    scene data: read and written through one-hot weights over the bodies."""
    num_bodies = len(position)
    pick_a = [(constant("joint_a", j) == body).astype(jnp.float32) for body in range(num_bodies)]
    pick_b = [(constant("joint_b", j) == body).astype(jnp.float32) for body in range(num_bodies)]

    def read(values: list, pick: list[Row]):
        if isinstance(values[0], tuple):
            return tuple(sum(w * v[c] for w, v in zip(pick, values, strict=True)) for c in range(2))
        return sum(w * v for w, v in zip(pick, values, strict=True))

    xa, xb = read(position, pick_a), read(position, pick_b)
    va, vb = read(velocity, pick_a), read(velocity, pick_b)
    wa, wb = read(spin, pick_a), read(spin, pick_b)
    on = constant("joint_enabled", j)
    enabled = on != 0
    ima, imb = constant("joint_inverse_mass_a", j), constant("joint_inverse_mass_b", j)
    iia, iib = constant("joint_inverse_inertia_a", j), constant("joint_inverse_inertia_b", j)
    ra, rb = constant_vector("joint_lever_a", j), constant_vector("joint_lever_b", j)

    anchor_a, anchor_b = _add(xa, ra), _add(xb, rb)
    mass_a, mass_b = 1.0 / _nonzero(ima), 1.0 / _nonzero(imb)
    point = tuple(
        jnp.where(ima == 0, anchor_a[c], jnp.where(
            imb == 0, anchor_b[c], (anchor_a[c] * mass_a + anchor_b[c] * mass_b) / (mass_a + mass_b)))
        for c in range(2)
    )
    arm_a, arm_b = _sub(point, xa), _sub(point, xb)
    relative = _sub(_add(vb, _spin_velocity(wb, arm_b)), _add(va, _spin_velocity(wa, arm_a)))
    speed = jnp.sqrt(relative[0] ** 2 + relative[1] ** 2)
    direction = (relative[0] / _nonzero(speed), relative[1] / _nonzero(speed))
    denominator = _nonzero(ima + imb) + _cross(ra, direction) ** 2 * iia + _cross(rb, direction) ** 2 * iib
    error = _sub(anchor_b, anchor_a)
    impulse = tuple(
        (p["joint_stiffness"] * (relative[c] + p["baumgarte_coefficient_joints_v"] * error[c])
         / _nonzero(denominator)) * on
        for c in range(2)
    )
    new_wa, new_wb = wa + iia * _cross(ra, impulse), wb - iib * _cross(rb, impulse)
    share = tuple(p["baumgarte_coefficient_joints_p"] * error[c] / _nonzero(ima + imb) for c in range(2))

    raw = new_wb - new_wa
    phi = constant("joint_relative_angle", j)
    fixed = constant("joint_is_fixed_joint", j) != 0
    limit_error = phi - jnp.clip(phi, constant("joint_min_rotation", j), constant("joint_max_rotation", j))
    limit_bias = p["baumgarte_coefficient_rjoint_limit_av"] * limit_error
    limited = (~fixed & (constant("joint_motor_has_joint_limits", j) != 0) & (limit_error != 0)
               & (jnp.sign(raw) == jnp.sign(limit_bias)))
    target = jnp.where(fixed, raw + p["baumgarte_coefficient_fjoint_av"] * phi, raw + limit_bias)
    angular_impulse = jnp.where(fixed | limited, target / _nonzero(iia + iib), 0.0) * on
    new_wa = new_wa + angular_impulse * iia
    new_wb = new_wb - angular_impulse * iib

    total = _add(acc[j], impulse)
    cap = CARRIED_IMPULSE_CAP * 2.0 * p["clip_velocity"] / _nonzero(ima + imb)
    norm = jnp.sqrt(total[0] ** 2 + total[1] ** 2)
    total = _scale(jnp.minimum(1.0, cap / _nonzero(norm)), total)
    r_cap = CARRIED_IMPULSE_CAP * 2.0 * p["clip_angular_velocity"] / _nonzero(iia + iib)
    total_r = jnp.clip(acc_r[j] + angular_impulse, -r_cap, r_cap)

    for body in range(num_bodies):
        wa_, wb_ = pick_a[body], pick_b[body]
        position[body] = tuple(
            position[body][c] + wa_ * (share[c] * ima) + wb_ * (-share[c] * imb) for c in range(2)
        )
        velocity[body] = tuple(
            velocity[body][c] + wa_ * (ima * impulse[c]) + wb_ * (-imb * impulse[c]) for c in range(2)
        )
        spin[body] = spin[body] + wa_ * (new_wa - wa) + wb_ * (new_wb - wb)
    acc[j] = tuple(jnp.where(enabled, total[c], 0.0) for c in range(2))
    acc_r[j] = jnp.where(enabled & fixed, total_r, 0.0)
    anchor[j] = tuple(jnp.where(enabled, point[c], 0.0) for c in range(2))
