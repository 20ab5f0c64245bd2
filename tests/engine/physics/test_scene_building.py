"""The slot writers of engine/physics/building.py, which the scene helpers and the level generator share: a write
fills one slot and activates it, slot -1 writes nothing, and a helper on a full array returns -1 and leaves the
scene as it was."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.physics import SceneSizes, add_circle, add_rectangle, add_revolute_joint, empty_scene
from impulse.engine.physics.building import write_body, write_joint

SIZES = SceneSizes(num_polygons=6, num_circles=1, num_joints=1, num_thrusters=0)


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def test_a_body_write_fills_one_slot_and_slot_minus_one_writes_nothing() -> None:
    bodies = empty_scene(SIZES).bodies
    values = dict(position=jnp.asarray([1.0, 2.0]), rotation=0.5, inverse_mass=2.0, inverse_inertia=3.0)
    assert _same(write_body(bodies, jnp.asarray(-1), **values), bodies)
    written = write_body(bodies, jnp.asarray(6), **values)
    assert bool(written.active[6]) and not bool(bodies.active[6])
    np.testing.assert_array_equal(written.position[6], [1.0, 2.0])
    assert float(written.inverse_mass[6]) == 2.0 and float(written.friction[6]) == 1.0
    others = np.arange(SIZES.num_bodies) != 6
    for new, old in zip(jax.tree.leaves(written), jax.tree.leaves(bodies), strict=True):
        np.testing.assert_array_equal(np.asarray(new)[others], np.asarray(old)[others])


def test_a_joint_write_keeps_the_fields_it_is_not_given() -> None:
    joints = empty_scene(SIZES).joints
    written = write_joint(joints, jnp.asarray(0), a_index=4, b_index=5, is_fixed_joint=True)
    assert bool(written.active[0]) and bool(written.is_fixed_joint[0]) and int(written.b_index[0]) == 5
    np.testing.assert_array_equal(written.min_rotation, joints.min_rotation)


def test_helpers_on_a_full_array_return_minus_one_and_change_nothing() -> None:
    state, first = add_circle(empty_scene(SIZES), (1.0, 1.0), 0.2)
    state, box = add_rectangle(state, (3.0, 1.0), 0.4, 0.4)
    state, joint = add_revolute_joint(state, box, first, (0.0, 0.0), (0.0, 0.0))
    assert int(first) == SIZES.num_polygons and int(box) == SIZES.num_static_polygons and int(joint) == 0
    last_box, index = add_rectangle(state, (2.0, 3.0), 0.2, 0.2)
    assert int(index) == SIZES.num_polygons - 1
    for before, (after, index) in (
        (last_box, add_rectangle(last_box, (2.0, 4.0), 0.2, 0.2)),
        (state, add_circle(state, (2.0, 2.0), 0.1)),
        (state, add_revolute_joint(state, box, first, (0.1, 0.0), (0.0, 0.0))),
    ):
        assert int(index) == -1 and _same(after, before)
