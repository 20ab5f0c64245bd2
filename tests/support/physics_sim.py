"""Shared scene sizes and jitted simulation loops for the physics tests.

Every test uses the one `SIZES` below and runs through `run` (a jitted `lax.scan` over `CHUNK` steps), so the
step is compiled once for the whole suite and each test only pays for the steps it simulates. Longer runs call
`run` repeatedly (`simulate`); per-step records come back as numpy arrays.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.physics import SceneSizes, SimParams, SimState, SolverOptions, empty_scene, step
from impulse.engine.physics.pairs import pair_tables

SIZES = SceneSizes(num_polygons=8, num_circles=3, num_joints=2, num_thrusters=2)
NUM_ACTIONS = SIZES.num_joints + SIZES.num_thrusters
PARAMS = SimParams()
OPTIONS = SolverOptions()
DT = PARAMS.dt
G = 9.81
FLOOR_TOP = 0.4
CHUNK = 20  # steps per compiled call (a third of a simulated second); runs are multiples of it


class Trace(NamedTuple):
    """Per-step records after each step, leading axis = step."""

    position: np.ndarray  # [T, N, 2]
    rotation: np.ndarray  # [T, N]
    velocity: np.ndarray  # [T, N, 2]
    angular_velocity: np.ndarray  # [T, N]
    touching: np.ndarray  # [T, num_pairs]
    normal_impulse: np.ndarray  # [T, num_pairs]


def _scan_steps(
    state: SimState, params: SimParams, actions: jax.Array, sizes: SceneSizes, options: SolverOptions = OPTIONS
):
    """Step once per row of `actions` [T, A]; return the final state and the per-step records."""

    def body(s, a):
        s, contacts = step(s, params, a, sizes, options)
        b = s.bodies
        record = (
            b.position,
            b.rotation,
            b.velocity,
            b.angular_velocity,
            contacts.touching,
            contacts.normal_impulse,
        )
        return s, record

    return jax.lax.scan(body, state, actions)


run = jax.jit(_scan_steps, static_argnames=("sizes", "options"))
# A batch of scenes [B, ...] with actions [B, T, A]: the scan of the vmapped step (vmap outside the scan).
run_batch = jax.jit(jax.vmap(_scan_steps, in_axes=(0, None, 0, None)), static_argnames=("sizes",))
# One step of a batch of scenes, exactly `jax.vmap(step)`.
step_batch = jax.jit(jax.vmap(step, in_axes=(0, None, 0, None)), static_argnames=("sizes",))


def simulate(
    state: SimState, num_steps: int, actions=None, params: SimParams = PARAMS
) -> tuple[SimState, Trace]:
    """Run `num_steps` (a multiple of CHUNK) steps with fixed actions through the shared compiled `run`."""
    if num_steps % CHUNK:
        raise ValueError(f"num_steps must be a multiple of {CHUNK}, got {num_steps}")
    row = jnp.zeros(NUM_ACTIONS, jnp.float32) if actions is None else jnp.asarray(actions, jnp.float32)
    block = jnp.broadcast_to(row, (CHUNK, NUM_ACTIONS))
    records = []
    for _ in range(num_steps // CHUNK):
        state, record = run(state, params, block, SIZES)
        records.append(record)
    trace = Trace(*(np.concatenate([np.asarray(r[i]) for r in records]) for i in range(len(Trace._fields))))
    return state, trace


def open_scene() -> SimState:
    """The shared size with the arena slots switched off: nothing but what the test adds."""
    return empty_scene(SIZES, arena=False)


def arena_scene() -> SimState:
    return empty_scene(SIZES, arena=True)


def pair_index(a, b) -> int:
    """Index of the pair of bodies a and b in the per-pair arrays (StepContacts, pair_collides)."""
    return _pair_index(int(a), int(b))


@functools.cache
def _pair_index(a: int, b: int) -> int:
    tables = pair_tables(SIZES)
    for k, (pa, pb) in enumerate(zip(tables.pair_a, tables.pair_b)):
        if {int(pa), int(pb)} == {a, b}:
            return k
    raise KeyError((a, b))


def set_body_field(state: SimState, field: str, index: int, value) -> SimState:
    arr = getattr(state.bodies, field)
    return state.replace(bodies=state.bodies.replace(**{field: arr.at[index].set(value)}))


def mass(state: SimState, index: int) -> float:
    return 1.0 / float(state.bodies.inverse_mass[index])


def inertia(state: SimState, index: int) -> float:
    return 1.0 / float(state.bodies.inverse_inertia[index])


def zero_gravity(state: SimState) -> SimState:
    return state.replace(gravity=jnp.zeros(2, jnp.float32))


def stack(states: list[SimState]) -> SimState:
    """A batch (leading axis) from single scenes of the same sizes."""
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *states)


def take(batch: SimState, index: int) -> SimState:
    return jax.tree.map(lambda leaf: leaf[index], batch)


def non_finite_leaves(state) -> list[str]:
    """Paths of the float leaves of a pytree that hold a NaN or an infinity."""
    bad = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(state):
        arr = np.asarray(leaf)
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            bad.append(jax.tree_util.keystr(path))
    return bad
