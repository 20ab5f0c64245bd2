"""One physics step of one scene: `step(state, params, actions, sizes, options)`; jit it with `sizes` and `options`
static, vmap it over scenes.

The step is a sequence of named stages, in Jax2D's order:

1. `apply_gravity`;
2. `prepare_constraints`: detection, per-contact and per-joint solver constants (the step's `StepContext`), last
   step's impulses where contacts persist;
3. motors and thrusters (actuators.py);
4. `warm_start_all`: last step's contact and joint impulses re-applied;
5. `solve`: `options.iterations` sweeps of `solve_joints` (slot order) then the contacts;
6. `integrate`: velocity clamps, symplectic Euler, position clamp;
7. `store_impulses`: what the next step warm-starts from.

Every stage after the second reads the step's constants from one `StepContext` (context.py). `options.schedule`
picks how contacts are swept in stage 5: phase by phase with per-step lever arms (`iterate_phased`, the default,
faster) or as Jax2D does, in sorted Jacobi batches with lever arms that follow the joints' position corrections
(`iterate_jax2d`, see docs/engine.md; "jax2d_wipe" adds Jax2D's padding bug, for comparisons only).
`options.backend="pallas"` runs the phased iterations as one fused GPU kernel (`iterate_fused`, solver_kernel.py).
Which slot is which, and how values reach bodies, is slots.py's.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.physics.actuators import apply_motors, apply_thrusters, thruster_positions
from impulse.engine.physics.batched_contacts import batch_slots, solve_contacts
from impulse.engine.physics.contact_solver import ContactRows, contact_rows, solve_phase, warm_start
from impulse.engine.physics.context import Impulses, StepContext
from impulse.engine.physics.joint_solver import JointSolverState, joint_rows, solve_joint, warm_start_joints
from impulse.engine.physics.narrowphase import detect_contacts
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.params import CARRIED_IMPULSE_CAP, SimParams
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.slots import by_phase, in_slot_order, phase_bodies, point0_slots
from impulse.engine.physics.solver_kernel import iterate_kernel
from impulse.engine.physics.state import ContactCache, SimState

Array = jax.Array

DEFAULT_OPTIONS = SolverOptions()


class StepContacts(NamedTuple):
    """What the task layer needs to know about touching shapes after a step, one entry per pair
    (see `pairs.pair_tables(sizes).pair_a / pair_b` for the bodies of each pair)."""

    touching: Array  # [num_pairs] bool: geometric overlap (point 0), joints notwithstanding, as Kinetix reads it
    normal: Array  # [num_pairs, 2]
    point: Array  # [num_pairs, 2]
    normal_impulse: Array  # [num_pairs] accumulated normal impulse of point 0


def step(
    state: SimState,
    params: SimParams,
    actions: Array,
    sizes: SceneSizes,
    options: SolverOptions = DEFAULT_OPTIONS,
) -> tuple[SimState, StepContacts]:
    """Advance one scene by params.dt.

    `actions` has num_joints motor actions (Kinetix clips them to [-1, 1]) followed by num_thrusters thruster
    actions ([0, 1]).
    """
    actions = jnp.asarray(actions, dtype=jnp.float32)
    motor_actions, thruster_actions = actions[: sizes.num_joints], actions[sizes.num_joints :]

    velocity = apply_gravity(state, params)
    context, carried = prepare_constraints(state, velocity, params, sizes, options)
    angular_velocity = apply_motors(state.bodies.angular_velocity, state, context.joint_rows, motor_actions, params)
    velocity, angular_velocity = apply_thrusters(velocity, angular_velocity, state, thruster_actions, params)
    start = warm_start_all(velocity, angular_velocity, state, carried, context)
    solved, impulses = solve(start, carried, context)
    new_state = integrate(state, solved, params)
    cache = store_impulses(impulses, context)
    return new_state.replace(contacts=cache), pair_contacts(cache, context)


def apply_gravity(state: SimState, params: SimParams) -> Array:
    """Velocities after one step of gravity on every active dynamic body."""
    bodies = state.bodies
    falls = (bodies.inverse_mass != 0) & bodies.active
    return bodies.velocity + jnp.where(falls[:, None], state.gravity * params.dt, 0.0)


def prepare_constraints(
    state: SimState, velocity: Array, params: SimParams, sizes: SceneSizes, options: SolverOptions
) -> tuple[StepContext, Impulses]:
    """Detect every contact slot and compute the per-contact and per-joint constants the later stages read (the
    step's context); carry over last step's contact impulses where the contact persists (and warm starting is
    on)."""
    tables = pair_tables(sizes)
    contacts = detect_contacts(state, tables)
    rows, enabled = contact_rows(state, velocity, contacts, tables, params)
    carried = enabled & state.contacts.active & options.warm_starting
    impulses = Impulses(
        normal=jnp.where(carried, state.contacts.normal_impulse, 0.0),
        tangent=jnp.where(carried, state.contacts.tangent_impulse, 0.0),
    )
    context = StepContext(
        params=params, joints=state.joints, joint_rows=joint_rows(state), contacts=contacts, contact_rows=rows,
        enabled=enabled, sizes=sizes, options=options,
    )
    return context, impulses


def warm_start_all(
    velocity: Array, angular_velocity: Array, state: SimState, carried: Impulses, context: StepContext
) -> JointSolverState:
    """Re-apply last step's contact and joint impulses; the solver's starting state."""
    joints = context.joints
    if context.options.warm_starting:
        velocity, angular_velocity = warm_start(
            velocity, angular_velocity, context.contact_rows, carried.normal, carried.tangent, context.tables
        )
        velocity, angular_velocity = warm_start_joints(velocity, angular_velocity, context.joint_rows, joints)
        acc_impulse, acc_r_impulse = joints.acc_impulse, joints.acc_r_impulse
    else:
        acc_impulse, acc_r_impulse = jnp.zeros_like(joints.acc_impulse), jnp.zeros_like(joints.acc_r_impulse)
    return JointSolverState(
        position=state.bodies.position,
        velocity=velocity,
        angular_velocity=angular_velocity,
        acc_impulse=acc_impulse,
        acc_r_impulse=acc_r_impulse,
        anchor=joints.global_position,
    )


def solve(start: JointSolverState, carried: Impulses, context: StepContext) -> tuple[JointSolverState, Impulses]:
    """The solver iterations, in the schedule and on the backend that `context.options` pick."""
    options = context.options
    if options.schedule in ("jax2d", "jax2d_wipe"):
        return iterate_jax2d(start, carried, context)
    if options.backend == "xla":
        return iterate_phased(start, carried, context)
    return iterate_fused(start, carried, context)


def solve_joints(joint_state: JointSolverState, context: StepContext) -> JointSolverState:
    """One Gauss-Seidel sweep over the joints in slot order."""
    for j in range(context.sizes.num_joints):
        joint_state = solve_joint(joint_state, j, context.joint_rows, context.joints, context.params)
    return joint_state


def solve_contacts_phased(
    joint_state: JointSolverState, impulses: list[Impulses], phase_rows: list[ContactRows], context: StepContext
) -> tuple[JointSolverState, list[Impulses]]:
    """One Gauss-Seidel sweep over the contacts, phase after phase (the contacts of a phase side by side);
    `impulses` and `phase_rows` hold one entry per phase."""
    velocity, angular_velocity = joint_state.velocity, joint_state.angular_velocity
    solved = []
    bodies_of_phase = phase_bodies(context.tables)
    for rows, (body_a, body_b), (normal, tangent) in zip(phase_rows, bodies_of_phase, impulses, strict=True):
        velocity, angular_velocity, normal, tangent = solve_phase(
            velocity, angular_velocity, rows, body_a, body_b, normal, tangent
        )
        solved.append(Impulses(normal, tangent))
    return joint_state._replace(velocity=velocity, angular_velocity=angular_velocity), solved


def iterate_phased(
    start: JointSolverState, carried: Impulses, context: StepContext
) -> tuple[JointSolverState, Impulses]:
    """The default schedule: per iteration, joints in slot order, then contacts phase by phase, with lever arms
    and effective masses fixed per step (cheaper; the joints' position projection does not reach them)."""
    tables = context.tables
    split = (by_phase(field, tables) for field in context.contact_rows)
    phase_rows = [ContactRows(*fields) for fields in zip(*split, strict=True)]

    def iteration(_, carry):
        joint_state, impulses = carry
        joint_state = solve_joints(joint_state, context)
        return solve_contacts_phased(joint_state, impulses, phase_rows, context)

    per_phase = [Impulses(*pair) for pair in zip(by_phase(carried.normal, tables), by_phase(carried.tangent, tables),
                                                 strict=True)]
    solved, per_phase = jax.lax.fori_loop(0, context.options.iterations, iteration, (start, per_phase))
    if not tables.num_contacts:
        return solved, carried
    return solved, Impulses(
        normal=in_slot_order([p.normal for p in per_phase], tables),
        tangent=in_slot_order([p.tangent for p in per_phase], tables),
    )


def iterate_fused(
    start: JointSolverState, carried: Impulses, context: StepContext
) -> tuple[JointSolverState, Impulses]:
    """`iterate_phased` as the fused Pallas kernel where the step is compiled for a CUDA GPU, and as itself on
    every other platform (the kernel is written for Triton); with `backend="pallas_interpret"`, the kernel through
    Pallas's interpreter everywhere."""
    if context.options.backend == "pallas_interpret":
        return iterate_kernel(start, carried, context, interpret=True)

    def kernel(start: JointSolverState, carried: Impulses, context: StepContext):
        return iterate_kernel(start, carried, context, interpret=False)

    return jax.lax.platform_dependent(start, carried, context, cuda=kernel, default=iterate_phased)


def iterate_jax2d(
    start: JointSolverState, carried: Impulses, context: StepContext
) -> tuple[JointSolverState, Impulses]:
    """Jax2D's schedule (batched_contacts.py): per iteration, joints in slot order, then contacts in sorted Jacobi
    batches of 16, kind by kind, with lever arms and effective masses taken from the current positions at every
    visit."""
    tables = context.tables
    wipe = context.options.schedule == "jax2d_wipe"
    batches = batch_slots(tables, context.contacts.touching, wipe) if tables.num_contacts else []

    def iteration(_, carry):
        joint_state, impulses = carry
        joint_state = solve_joints(joint_state, context)
        return solve_contacts(joint_state, impulses, batches, context)

    return jax.lax.fori_loop(0, context.options.iterations, iteration, (start, carried))


def integrate(state: SimState, solved: JointSolverState, params: SimParams) -> SimState:
    """Clamp the solved velocities, move the bodies by them (symplectic Euler) and clamp positions; joints keep
    their accumulated impulses and anchors, thrusters follow their bodies."""
    bodies, joints = state.bodies, state.joints
    velocity = jnp.clip(solved.velocity, -params.clip_velocity, params.clip_velocity)
    angular_velocity = jnp.clip(solved.angular_velocity, -params.clip_angular_velocity, params.clip_angular_velocity)
    # Integrate with the clamped velocities (Jax2D integrates first): a body pinned at the position clamp by a
    # joint otherwise gains unbounded spin and ends in NaN.
    position = solved.position + velocity * params.dt
    rotation = bodies.rotation + angular_velocity * params.dt
    position = jnp.clip(position, -params.clip_position, params.clip_position)
    return state.replace(
        bodies=bodies.replace(
            position=position, rotation=rotation, velocity=velocity, angular_velocity=angular_velocity
        ),
        joints=joints.replace(
            acc_impulse=solved.acc_impulse, acc_r_impulse=solved.acc_r_impulse, global_position=solved.anchor
        ),
        thrusters=state.thrusters.replace(global_position=thruster_positions(state, position, rotation)),
    )


def store_impulses(impulses: Impulses, context: StepContext) -> ContactCache:
    """What the next step's warm start reads: the accumulated impulses and which contacts touched.

    What is carried is capped at `CARRIED_IMPULSE_CAP` times the impulse that takes the contact across the whole
    velocity clamp: letting it accumulate without bound (bodies pressed together on the position clamp) grows it
    geometrically into inf/NaN. Inactive in ordinary contact."""
    normal, tangent = impulses
    rows, params = context.contact_rows, context.params
    if context.tables.num_contacts:
        reach = jnp.sqrt((rows.lever_a**2).sum(-1)) + jnp.sqrt((rows.lever_b**2).sum(-1))
        crossing = 2.0 * (params.clip_velocity + params.clip_angular_velocity * reach) * rows.normal_mass
        cap = CARRIED_IMPULSE_CAP * crossing
        normal = jnp.minimum(normal, cap)
        tangent = jnp.clip(tangent, -rows.friction * normal, rows.friction * normal)
    return ContactCache(normal_impulse=normal, tangent_impulse=tangent, active=context.contacts.touching)


def pair_contacts(cache: ContactCache, context: StepContext) -> StepContacts:
    """What the task layer reads after the step: point 0 of every pair, with its stored normal impulse."""
    first = point0_slots(context.tables)
    contacts = context.contacts
    return StepContacts(
        touching=contacts.touching[first],
        normal=contacts.normal[first],
        point=contacts.point[first],
        normal_impulse=cache.normal_impulse[first],
    )
