"""The `schedule="jax2d"` solver option (SolverOptions.schedule): its batch layout, conservation, and agreement with
the default schedule where the visiting order cannot matter; and `schedule="jax2d_wipe"`, which adds Jax2D's
padding bug B1."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.physics import SolverOptions, add_circle, add_rectangle, add_revolute_joint
from impulse.engine.physics.batched_contacts import BATCH, batch_slots
from impulse.engine.physics.pairs import pair_tables
from tests.support.physics_sim import (
    CHUNK,
    DT,
    FLOOR_TOP,
    NUM_ACTIONS,
    PARAMS,
    SIZES,
    G,
    arena_scene,
    mass,
    open_scene,
    pair_index,
    run,
    zero_gravity,
)

PHASED = SolverOptions()
JAX2D = SolverOptions(schedule="jax2d")
JAX2D_WIPE = SolverOptions(schedule="jax2d_wipe")


def _positions(state, options: SolverOptions, chunks: int = 3) -> tuple[np.ndarray, np.ndarray]:
    actions = jnp.zeros((CHUNK, NUM_ACTIONS), jnp.float32)
    positions, velocities = [], []
    for _ in range(chunks):
        state, record = run(state, PARAMS, actions, SIZES, options)
        positions.append(np.asarray(record[0]))
        velocities.append(np.asarray(record[2]))
    return np.concatenate(positions), np.concatenate(velocities)


def test_unknown_schedule_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown solver schedule"):
        SolverOptions(schedule="jacobi")  # type: ignore[arg-type]


def test_batches_put_touching_pairs_last_and_deal_them_round_robin() -> None:
    tables = pair_tables(SIZES)
    touching = np.zeros(tables.num_contacts, bool)
    first_cr = 2 * tables.num_rr
    touching[[first_cr + 1, first_cr + 5, first_cr + 20]] = True
    touching[tables.num_rr + 2] = True  # point 1 of polygon pair 2 marks the whole pair touching
    batches = [np.asarray(b.slots) for b in batch_slots(tables, jnp.asarray(touching))]
    rr0, rr1, cr, cc = batches
    assert cr.shape == (-(-tables.num_cr // BATCH), BATCH)
    # The list is the stable touching-last order plus padding (slot K), dealt out column by column.
    listed = cr.T.reshape(-1)
    real = listed[listed < tables.num_contacts]
    assert real[-3:].tolist() == [first_cr + 1, first_cr + 5, first_cr + 20]
    assert sorted(real.tolist()) == list(range(first_cr, first_cr + tables.num_cr))
    assert (listed[len(real):] == tables.num_contacts).all()
    # Both points of the polygon pairs share one order, with pair 2 last.
    assert rr0.T.reshape(-1)[tables.num_rr - 1] == 2 and rr1.T.reshape(-1)[tables.num_rr - 1] == tables.num_rr + 2
    assert cc.shape == (1, BATCH)


def test_momentum_is_conserved_through_contacts_and_a_joint() -> None:
    # No gravity, no arena: a jointed pair of circles runs into a box; every impulse is internal.
    state = zero_gravity(open_scene())
    state, box = add_rectangle(state, (2.0, 2.0), 0.5, 0.5, velocity=(-1.0, 0.0))
    state, c1 = add_circle(state, (1.0, 2.1), 0.2, velocity=(1.5, 0.0))
    state, c2 = add_circle(state, (0.6, 2.1), 0.2, velocity=(1.5, 0.3))
    state, _ = add_revolute_joint(state, c1, c2, (-0.2, 0.0), (0.2, 0.0))
    positions, velocities = _positions(state, JAX2D)
    inverse_mass = np.asarray(state.bodies.inverse_mass)
    moving = np.asarray(state.bodies.active) & (inverse_mass > 0)
    mass = 1.0 / np.where(moving, inverse_mass, 1.0)
    momentum = (velocities[:, moving] * mass[moving, None]).sum(axis=1)
    initial = (np.asarray(state.bodies.velocity)[moving] * mass[moving, None]).sum(axis=0)
    gap = np.linalg.norm(positions[:, int(box)] - positions[:, int(c1)], axis=1)
    assert gap.min() < 0.5, "the circles never reached the box"
    np.testing.assert_allclose(momentum, np.broadcast_to(initial, momentum.shape), atol=1e-4)


def test_without_joints_or_shared_bodies_the_two_schedules_agree() -> None:
    # A box and a circle land side by side on the floor: every contact touches one dynamic body, and no joint
    # moves a body during the iterations, so the visiting order and the per-visit lever arms cannot matter.
    state = arena_scene()
    state, box = add_rectangle(state, (1.5, 0.8), 0.6, 0.3, rotation=0.2)
    state, ball = add_circle(state, (3.0, 0.9), 0.25, velocity=(0.5, 0.0))
    phased, _ = _positions(state, PHASED)
    jax2d, _ = _positions(state, JAX2D)
    assert phased[-1, int(box), 1] < 0.8 - 0.1, "the box did not fall onto the floor"
    np.testing.assert_allclose(jax2d[:, [int(box), int(ball)]], phased[:, [int(box), int(ball)]], atol=1e-4)


def test_the_wipe_names_each_kinds_last_slot_in_the_batches_that_hold_padding() -> None:
    tables = pair_tables(SIZES)
    touching = jnp.zeros(tables.num_contacts, bool)
    first = {"rr0": 0, "rr1": tables.num_rr, "cr": 2 * tables.num_rr, "cc": 2 * tables.num_rr + tables.num_cr}
    counts = {"rr0": tables.num_rr, "rr1": tables.num_rr, "cr": tables.num_cr, "cc": tables.num_cc}
    plain = batch_slots(tables, touching)
    wiped = batch_slots(tables, touching, wipe=True)
    for name, kind, bugged in zip(counts, plain, wiped):
        slots = np.asarray(bugged.slots)
        np.testing.assert_array_equal(slots, np.asarray(kind.slots))
        assert (np.asarray(kind.wiped) == tables.num_contacts).all(), "without the wipe no batch names a slot"
        holds_padding = (slots == tables.num_contacts).any(axis=1)
        last = first[name] + counts[name] - 1
        expected = np.where(holds_padding, last, tables.num_contacts)
        np.testing.assert_array_equal(np.asarray(bugged.wiped), expected, err_msg=name)


def test_the_wipe_drops_the_last_pairs_resting_impulse() -> None:
    # Three circles: the last circle-circle pair is (second, third). The third rests on the second, which rests
    # on the floor. Without the bug the pair's accumulated impulse per step is the top circle's weight times dt;
    # Jax2D's padding write zeroes it after every batch, so it is stored as 0 (Jax2D digest, bug B1).
    radius = 0.2
    state = arena_scene()
    state, _ = add_circle(state, (1.0, FLOOR_TOP + radius), radius)
    state, lower = add_circle(state, (3.0, FLOOR_TOP + radius), radius)
    state, upper = add_circle(state, (3.0, FLOOR_TOP + 3 * radius), radius)
    pair = pair_index(lower, upper)
    actions = jnp.zeros((CHUNK, NUM_ACTIONS), jnp.float32)
    stored = {}
    for options in (JAX2D, JAX2D_WIPE):
        s = state
        for _ in range(3):
            s, record = run(s, PARAMS, actions, SIZES, options)
        touching, impulse = np.asarray(record[4])[:, pair], np.asarray(record[5])[:, pair]
        assert touching.all(), f"{options.schedule}: the stack came apart"
        stored[options.schedule] = impulse
    weight_impulse = mass(state, int(upper)) * G * DT
    np.testing.assert_allclose(stored["jax2d"], weight_impulse, rtol=0.1)
    np.testing.assert_array_equal(stored["jax2d_wipe"], 0.0)
