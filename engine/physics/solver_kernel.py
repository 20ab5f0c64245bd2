"""Stage 5 of the step, the solver iterations, as one Pallas kernel per block of scenes (`backend="pallas"`).

Why: on a GPU the XLA step runs every joint visit and every contact phase of every iteration as its own chain of
small kernels that read and write the bodies in global memory; a Kinetix scene is 1-2 KB, so the step is bound
by launches and memory traffic (docs/engine.md). Here one kernel launch runs all `options.iterations` sweeps of a
block of scenes (one per lane), on a copy of their state that stays with the block.

What it computes is `step.iterate_phased`, visit for visit: per iteration the joints in slot order
(joint_solver.solve_joint), then the contacts phase by phase (contact_solver.solve_phase). The contact visit is the
XLA step's own, `contact_solver.visit_contact`, on lanes (`lanes.LANES`); the joint visit is `visit_joint` below,
joint_solver.solve_joint's formulas written over lanes. tests/engine/physics/test_physics_kernel.py holds the
kernel to the XLA schedule on levels and random scenes.

Rolled, so that the program Triton compiles does not grow with the scene: every loop is a loop of the kernel
(`jax.lax.fori_loop`, an scf.for in Triton), none is unrolled at trace time. The kernel body holds one joint visit
and one contact visit:

1. copy the block's state (bodies, joint accumulators, contact impulses) to the output block;
2. `iterations` times: the joints in slot order, then the contacts in visit order, phase after phase. A phase's
   contacts share no body, so visiting them one after another gives, bit for bit, what solving them side by side
   gives, and one loop over all contacts in phase order is the whole contact sweep.

Each visit loads the rows it reads from the output block at computed row offsets (lanes.py) and stores the rows it
changed; its constants are read from the constants block the same way. A contact's bodies are static: a table of
the bodies of each contact in visit order (an int32 input shared by all blocks) gives them as scalars, and their
rows are loaded for all lanes alike. A joint's bodies are scene data: each lane reads and writes its own bodies'
rows (a gather and a scatter). A lane is one scene and one GPU thread (blocks of 32 to 128 lanes, one warp per 32),
so each load sees the stores of the visits before it from the same thread: the Gauss-Seidel order needs no barrier.
(That is also why a phase is not one vectorised update over a [contacts, lanes] tile: Triton may spread a tile's
scene over several threads, and the next phase would read bodies that another thread wrote.)
The kernel is written for Triton (`jax.experimental.pallas.triton`); on other platforms `step` runs the XLA schedule
instead, and `interpret=True` runs the kernel through Pallas's interpreter anywhere (for tests).

The kernel works on a batch of scenes, the step on one: `iterate_kernel` is a `custom_vmap`, whose batching
rule hands the whole vmapped batch to the kernel with scenes on lanes; unbatched it runs one scene in one block.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pallas_triton

from impulse.engine.physics.contact_solver import ContactRows, visit_contact
from impulse.engine.physics.context import Impulses, StepContext
from impulse.engine.physics.joint_solver import JointSolverState
from impulse.engine.physics.lanes import (
    LANES,
    Field,
    Row,
    RowLayout,
    Vector,
    add,
    cross,
    lane_numbers,
    nonzero,
    scale,
    spin_velocity,
    sub,
)
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.params import CARRIED_IMPULSE_CAP
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.slots import by_phase, in_slot_order, phase_bodies

Array = jax.Array

MAX_LANES = 128
MIN_LANES = 32
"""Scenes per block: one per thread, from one warp to four; never fewer lanes than a warp has threads, so that no
scene's values are held by two threads."""

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
def layouts(sizes: SceneSizes) -> tuple[RowLayout, RowLayout, RowLayout]:
    """(state, constants, schedule): what the iterations change and what they only read, per scene (contacts in
    visit order), and the bodies of each contact in visit order, the same for every scene."""
    n, j, k = sizes.num_bodies, sizes.num_joints, pair_tables(sizes).num_contacts
    state = RowLayout((
        Field("position", n, 2), Field("velocity", n, 2), Field("angular_velocity", n),
        Field("acc_impulse", j, 2), Field("acc_r_impulse", j), Field("anchor", j, 2),
        Field("normal_impulse", k), Field("tangent_impulse", k),
    ))
    contact = tuple(Field(f"contact_{name}", k, 2 if name in VECTOR_CONTACT_FIELDS else 1) for name in CONTACT_FIELDS)
    joint = (Field("joint_a", j), Field("joint_b", j), Field("joint_lever_a", j, 2), Field("joint_lever_b", j, 2))
    joint += tuple(Field(f"joint_{name}", j) for name in JOINT_SCALARS)
    constants = RowLayout(contact + joint + (Field("params", len(SOLVER_PARAMS)),))
    schedule = RowLayout((Field("contact_a", k), Field("contact_b", k)))
    return state, constants, schedule


@functools.cache
def schedule_table(sizes: SceneSizes) -> np.ndarray:
    """The `schedule` layout's table: body a and body b of every contact, in visit order (phase after phase)."""
    _, _, schedule = layouts(sizes)
    table = np.zeros(schedule.num_rows, np.int32)
    bodies = phase_bodies(pair_tables(sizes))
    if bodies:
        for name, side in (("contact_a", 0), ("contact_b", 1)):
            order = np.concatenate([pair[side] for pair in bodies])
            table[schedule.offsets[name] : schedule.offsets[name] + len(order)] = order
    return table


def iterate_kernel(
    start: JointSolverState, carried: Impulses, context: StepContext, interpret: bool = False
) -> tuple[JointSolverState, Impulses]:
    """`step.iterate_phased` for one scene (vmap it: batches run as blocks of scenes): the solved joint state and
    the accumulated contact impulses in slot order."""
    rows, jrows, joints, params = context.contact_rows, context.joint_rows, context.joints, context.params
    tables = context.tables

    def in_visit_order(values: Array) -> Array:
        return jnp.concatenate(by_phase(values, tables)) if tables.num_contacts else values

    def in_slot_order_of(values: Array) -> Array:
        return in_slot_order([values], tables) if tables.num_contacts else values

    state_fields = {
        "position": start.position, "velocity": start.velocity, "angular_velocity": start.angular_velocity,
        "acc_impulse": start.acc_impulse, "acc_r_impulse": start.acc_r_impulse, "anchor": start.anchor,
        "normal_impulse": in_visit_order(carried.normal), "tangent_impulse": in_visit_order(carried.tangent),
    }
    constant_fields = {
        f"contact_{name}": in_visit_order(value) for name, value in zip(CONTACT_FIELDS, rows, strict=True)
    }
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
    impulses = Impulses(in_slot_order_of(solved["normal_impulse"]), in_slot_order_of(solved["tangent_impulse"]))
    return joint_state, impulses


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
    """The kernel over a batch of scenes (leading axis of every field), in blocks of MIN_LANES to MAX_LANES
    scenes."""
    state_layout, constant_layout, schedule_layout = layouts(sizes)
    scenes = state_fields["position"].shape[0]
    shapes = {name: value.shape for name, value in state_fields.items()}
    lanes = min(MAX_LANES, max(MIN_LANES, 1 << (scenes - 1).bit_length()))
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
        in_specs=[
            block((state_layout.num_rows, lanes)),
            block((constant_layout.num_rows, lanes)),
            pl.BlockSpec((schedule_layout.num_rows,), lambda i: (0,)),
        ],
        out_specs=block((state_layout.num_rows, lanes)),
        compiler_params=pallas_triton.CompilerParams(num_warps=lanes // 32),
        interpret=interpret,
    )(state_in, constants, jnp.asarray(schedule_table(sizes)))
    solved = state_layout.unpack(state_out[:, :scenes])
    return {name: solved[name].reshape(shapes[name]) for name in shapes}


def solver_kernel(state_ref, constants_ref, schedule_ref, out_ref, *, sizes: SceneSizes, iterations: int) -> None:
    """All `iterations` solver sweeps of one block of scenes, as the module docstring lists them: the state copied
    to `out_ref`, then per sweep every joint in slot order and every contact in visit order, each visit loading and
    storing its own rows of `out_ref`."""
    state, constants, schedule = layouts(sizes)
    num_joints, num_contacts = sizes.num_joints, pair_tables(sizes).num_contacts
    p = {name: constants.row(constants_ref, "params", i) for i, name in enumerate(SOLVER_PARAMS)}
    lanes = lane_numbers(out_ref.shape[1])

    def copy_row(r: Array, carry: None) -> None:
        out_ref[r, :] = state_ref[r, :]
        return carry

    def joint(j: Array, carry: None) -> None:
        """Joint j of every lane: its bodies are each scene's own, so they are read and written per lane."""
        a = constants.row(constants_ref, "joint_a", j).astype(jnp.int32)
        b = constants.row(constants_ref, "joint_b", j).astype(jnp.int32)
        c = JointConstants(
            lever_a=constants.vector(constants_ref, "joint_lever_a", j),
            lever_b=constants.vector(constants_ref, "joint_lever_b", j),
            **{name: constants.row(constants_ref, f"joint_{name}", j) for name in JOINT_SCALARS},
        )
        xa, xb = (state.lane_vector(out_ref, "position", body, lanes) for body in (a, b))
        va, vb = (state.lane_vector(out_ref, "velocity", body, lanes) for body in (a, b))
        wa, wb = (state.lane_row(out_ref, "angular_velocity", body, lanes) for body in (a, b))
        acc, acc_r = state.vector(out_ref, "acc_impulse", j), state.row(out_ref, "acc_r_impulse", j)
        change = visit_joint(c, xa, xb, va, vb, wa, wb, acc, acc_r, p)

        # joint_solver adds each body's changes weighted by its one-hot weights (0 or 1), side a's then side b's; a
        # joint with both sides on one body gets both changes there, in that order, and both stores write that sum.
        same = (a == b).astype(jnp.float32)

        def moved(old_a: Row, old_b: Row, delta_a: Row, delta_b: Row) -> tuple[Row, Row]:
            return old_a + delta_a + same * delta_b, old_b + same * delta_a + delta_b

        for name, old_a, old_b, delta_a, delta_b in (
            ("position", xa, xb, change.dx_a, change.dx_b), ("velocity", va, vb, change.dv_a, change.dv_b),
        ):
            new_a, new_b = zip(*(moved(old_a[i], old_b[i], delta_a[i], delta_b[i]) for i in range(2)), strict=True)
            state.set_lane_vector(out_ref, name, a, lanes, new_a)
            state.set_lane_vector(out_ref, name, b, lanes, new_b)
        new_wa, new_wb = moved(wa, wb, change.dw_a, change.dw_b)
        state.set_lane_row(out_ref, "angular_velocity", a, lanes, new_wa)
        state.set_lane_row(out_ref, "angular_velocity", b, lanes, new_wb)
        state.set_vector(out_ref, "acc_impulse", j, change.acc)
        state.set_row(out_ref, "acc_r_impulse", j, change.acc_r)
        state.set_vector(out_ref, "anchor", j, change.anchor)
        return carry

    def contact(v: Array, carry: None) -> None:
        """The v-th contact in visit order, on every lane; its bodies are the table's, the same on every lane."""
        a, b = schedule.entry(schedule_ref, "contact_a", v), schedule.entry(schedule_ref, "contact_b", v)
        c = ContactRows(*(
            constants.vector(constants_ref, f"contact_{name}", v) if name in VECTOR_CONTACT_FIELDS
            else constants.row(constants_ref, f"contact_{name}", v)
            for name in CONTACT_FIELDS
        ))
        va, wa = state.vector(out_ref, "velocity", a), state.row(out_ref, "angular_velocity", a)
        vb, wb = state.vector(out_ref, "velocity", b), state.row(out_ref, "angular_velocity", b)
        normal, tangent = state.row(out_ref, "normal_impulse", v), state.row(out_ref, "tangent_impulse", v)
        va, wa, vb, wb, normal, tangent = visit_contact(LANES, c, va, wa, vb, wb, normal, tangent)
        state.set_vector(out_ref, "velocity", a, va)
        state.set_row(out_ref, "angular_velocity", a, wa)
        state.set_vector(out_ref, "velocity", b, vb)
        state.set_row(out_ref, "angular_velocity", b, wb)
        state.set_row(out_ref, "normal_impulse", v, normal)
        state.set_row(out_ref, "tangent_impulse", v, tangent)
        return carry

    def sweep(_: Array, carry: None) -> None:
        if num_joints:
            jax.lax.fori_loop(0, num_joints, joint, carry)
        if num_contacts:
            jax.lax.fori_loop(0, num_contacts, contact, carry)
        return carry

    jax.lax.fori_loop(0, state.num_rows, copy_row, None)
    jax.lax.fori_loop(0, iterations, sweep, None)


class JointConstants(NamedTuple):
    """One joint's constants on every lane (the kernel's rows of joint_solver.JointRows and the joints' limits)."""

    lever_a: Vector
    lever_b: Vector
    inverse_mass_a: Row
    inverse_mass_b: Row
    inverse_inertia_a: Row
    inverse_inertia_b: Row
    relative_angle: Row
    enabled: Row
    is_fixed_joint: Row
    motor_has_joint_limits: Row
    min_rotation: Row
    max_rotation: Row


class JointChange(NamedTuple):
    """What one joint visit does: its bodies' position, velocity and spin changes, and the joint's new values."""

    dx_a: Vector
    dx_b: Vector
    dv_a: Vector
    dv_b: Vector
    dw_a: Row
    dw_b: Row
    acc: Vector
    acc_r: Row
    anchor: Vector


def visit_joint(c: JointConstants, xa: Vector, xb: Vector, va: Vector, vb: Vector, wa: Row, wb: Row, acc: Vector,
                acc_r: Row, p: dict[str, Row]) -> JointChange:
    """joint_solver.solve_joint for one joint on every lane, from its bodies' positions, velocities and spins and
    its accumulators: the linear impulse and position projection, then the angular lock or limit."""
    on = c.enabled
    enabled = on != 0
    ima, imb = c.inverse_mass_a, c.inverse_mass_b
    iia, iib = c.inverse_inertia_a, c.inverse_inertia_b
    ra, rb = c.lever_a, c.lever_b

    anchor_a, anchor_b = add(xa, ra), add(xb, rb)
    a_is_static, b_is_static = ima == 0, imb == 0
    mass_a, mass_b = 1.0 / nonzero(ima), 1.0 / nonzero(imb)
    point = tuple(
        jnp.where(a_is_static, anchor_a[i], jnp.where(
            b_is_static, anchor_b[i], (anchor_a[i] * mass_a + anchor_b[i] * mass_b) / (mass_a + mass_b)))
        for i in range(2)
    )
    arm_a, arm_b = sub(point, xa), sub(point, xb)
    relative = sub(add(vb, spin_velocity(wb, arm_b)), add(va, spin_velocity(wa, arm_a)))
    speed = nonzero(jnp.sqrt(relative[0] ** 2 + relative[1] ** 2))
    direction = (relative[0] / speed, relative[1] / speed)
    inverse_mass = nonzero(ima + imb)
    inverse_inertia = nonzero(iia + iib)
    denominator = nonzero(inverse_mass + cross(ra, direction) ** 2 * iia + cross(rb, direction) ** 2 * iib)
    error = sub(anchor_b, anchor_a)
    impulse = tuple(
        (p["joint_stiffness"] * (relative[i] + p["baumgarte_coefficient_joints_v"] * error[i]) / denominator) * on
        for i in range(2)
    )
    new_wa, new_wb = wa + iia * cross(ra, impulse), wb - iib * cross(rb, impulse)
    share = tuple(p["baumgarte_coefficient_joints_p"] * error[i] / inverse_mass for i in range(2))

    raw = new_wb - new_wa
    phi = c.relative_angle
    fixed = c.is_fixed_joint != 0
    limit_error = phi - jnp.clip(phi, c.min_rotation, c.max_rotation)
    limit_bias = p["baumgarte_coefficient_rjoint_limit_av"] * limit_error
    limited = (~fixed & (c.motor_has_joint_limits != 0) & (limit_error != 0)
               & (jnp.sign(raw) == jnp.sign(limit_bias)))
    target = jnp.where(fixed, raw + p["baumgarte_coefficient_fjoint_av"] * phi, raw + limit_bias)
    angular_impulse = jnp.where(fixed | limited, target / inverse_inertia, 0.0) * on
    new_wa = new_wa + angular_impulse * iia
    new_wb = new_wb - angular_impulse * iib

    total = add(acc, impulse)
    cap = CARRIED_IMPULSE_CAP * 2.0 * p["clip_velocity"] / inverse_mass
    norm = jnp.sqrt(total[0] ** 2 + total[1] ** 2)
    total = scale(jnp.minimum(1.0, cap / nonzero(norm)), total)
    r_cap = CARRIED_IMPULSE_CAP * 2.0 * p["clip_angular_velocity"] / inverse_inertia
    total_r = jnp.clip(acc_r + angular_impulse, -r_cap, r_cap)

    return JointChange(
        dx_a=tuple(share[i] * ima for i in range(2)), dx_b=tuple(-share[i] * imb for i in range(2)),
        dv_a=tuple(ima * impulse[i] for i in range(2)), dv_b=tuple(-imb * impulse[i] for i in range(2)),
        dw_a=new_wa - wa, dw_b=new_wb - wb,
        acc=tuple(jnp.where(enabled, total[i], 0.0) for i in range(2)),
        acc_r=jnp.where(enabled & fixed, total_r, 0.0),
        anchor=tuple(jnp.where(enabled, point[i], 0.0) for i in range(2)),
    )
