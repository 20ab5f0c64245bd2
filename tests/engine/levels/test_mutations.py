"""ACCEL mutations: every operator keeps levels valid and does what it says; whole mutations of 1,000 levels keep
the task invariants, and the first 250 of them pass validate_scene.

The levels edited come from the random batches the generator's tests sample (`tests.support.level_samples`, one
compiled sampler per size for both files)."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED, level_id_values
from impulse.engine.levels.mutations import (
    EDIT_NAMES,
    MutationConfig,
    apply_edit,
    edit_weights,
    mutate_level,
    mutate_levels,
)
from tests.support.level_samples import SIZES, host_levels, problems, summary, to_host

# Per-operator tests run on L levels (room left for additions, fixed joints present), one compiled program for all
# operators (the operator index is traced): the first OP_COUNT levels of the shared L batch.
OP_SIZE = "l"
OP_COUNT = 256
OP_VALIDATED = 48
P = SIZES[OP_SIZE].num_polygons
S = SIZES[OP_SIZE].num_static_polygons


def first(levels, count: int):
    """The first `count` levels of a host batch (numpy slicing: no small compiled program per leaf)."""
    return jax.tree.map(lambda x: x[:count], levels)


_apply_batch = jax.jit(
    jax.vmap(lambda key, level, edit: apply_edit(key, level, SIZES[OP_SIZE], edit), in_axes=(0, 0, None))
)


@functools.cache
def edited(name: str):
    """(before, after) host batches of OP_COUNT L levels edited once by operator `name`."""
    before = first(host_levels(OP_SIZE), OP_COUNT)
    keys = jax.random.split(jax.random.key(EDIT_NAMES.index(name)), OP_COUNT)
    after = _apply_batch(keys, before, EDIT_NAMES.index(name))
    return before, to_host(after)


def _shapes(levels):
    shapes = levels.state.bodies.active.copy()
    shapes[:, :S] = False
    return shapes


def _joint_counts(levels):
    j = levels.state.joints
    counts = np.zeros(levels.roles.shape, np.int64)
    lv, sl = np.nonzero(j.active)
    np.add.at(counts, (lv, j.a_index[lv, sl]), 1)
    np.add.at(counts, (lv, j.b_index[lv, sl]), 1)
    return counts


@pytest.mark.parametrize("name", EDIT_NAMES)
def test_each_operator_keeps_levels_valid(name):
    before, after = edited(name)
    found = problems(after, OP_VALIDATED)
    assert not found, found[:10]
    counts = summary(after, SIZES[OP_SIZE])
    assert np.all(counts.green_all == 1) and np.all(counts.blue_all == 1)
    assert np.all(counts.red <= 1)
    # At most two joints per rectangle and one per circle; no circle-circle joint.
    joints = _joint_counts(after)
    assert joints[:, :P].max() <= 2 and joints[:, P:].max() <= 1
    j = after.state.joints
    assert not np.any(j.active & (j.a_index >= P) & (j.b_index >= P))
    if name not in ("add_free_shape", "add_connected_shape", "remove_shape"):
        assert np.array_equal(_shapes(after), _shapes(before)), "only shape additions and removals change shapes"
    if name not in ("swap_role", "add_free_shape", "add_connected_shape", "remove_shape"):
        assert np.array_equal(after.roles, before.roles)


def test_add_free_shape():
    before, after = edited("add_free_shape")
    room = ~_shapes(before)[:, S:].all(1)
    added = _shapes(after) & ~_shapes(before)
    assert np.array_equal(added.sum(1), room.astype(int)), "one shape more exactly when a slot was free"
    assert room.mean() > 0.5
    assert np.array_equal(after.state.joints.active, before.state.joints.active)
    new_roles = after.roles[added]
    assert np.all((new_roles == 0) | (new_roles == ROLE_RED))


def test_add_connected_shape():
    before, after = edited("add_connected_shape")
    shapes = _shapes(before)
    links = _joint_counts(before)
    poly_room = ~shapes[:, S:P].all(1)
    shape_room = ~shapes[:, S:].all(1)
    joint_room = ~before.state.joints.active.all(1)
    rect_target = (shapes[:, :P] & (links[:, :P] < 2)).any(1)
    circle_target = (shapes[:, P:] & (links[:, P:] == 0)).any(1) & poly_room
    expected = shape_room & joint_room & (rect_target | circle_target)
    new_shapes = (_shapes(after) & ~shapes).sum(1)
    new_joints = after.state.joints.active.sum(1) - before.state.joints.active.sum(1)
    assert np.array_equal(new_shapes, expected.astype(int))
    assert np.array_equal(new_joints, expected.astype(int))
    assert expected.mean() > 0.5
    # The new joint holds the new shape.
    j = after.state.joints
    fresh = j.active & ~before.state.joints.active
    lv, sl = np.nonzero(fresh)
    added = _shapes(after) & ~shapes
    assert np.all(added[lv, j.a_index[lv, sl]] | added[lv, j.b_index[lv, sl]])


def test_remove_joint():
    before, after = edited("remove_joint")
    had = before.state.joints.active.any(1)
    removed = before.state.joints.active.sum(1) - after.state.joints.active.sum(1)
    assert np.array_equal(removed, had.astype(int))


def test_remove_shape_spares_green_and_blue():
    before, after = edited("remove_shape")
    shapes = _shapes(before)
    removable = (shapes & (before.roles != ROLE_GREEN) & (before.roles != ROLE_BLUE)).any(1)
    gone = shapes & ~_shapes(after)
    assert np.array_equal(gone.sum(1), removable.astype(int))
    lv, body = np.nonzero(gone)
    assert not np.any((before.roles[lv, body] == ROLE_GREEN) | (before.roles[lv, body] == ROLE_BLUE))
    # Its joints and thrusters went with it.
    j, t = after.state.joints, after.state.thrusters
    for i, b in zip(lv, body, strict=True):
        assert not np.any(j.active[i] & ((j.a_index[i] == b) | (j.b_index[i] == b)))
        assert not np.any(t.active[i] & (t.body_index[i] == b))


def test_swap_role_keeps_the_roles():
    before, after = edited("swap_role")
    shapes = _shapes(before)
    changed = (after.roles != before.roles).sum(1)
    distinct = np.array([len(np.unique(before.roles[i][shapes[i]])) for i in range(len(shapes))])
    assert np.array_equal(changed, np.where(distinct >= 2, 2, 0))
    for i in range(len(shapes)):
        assert sorted(after.roles[i][shapes[i]]) == sorted(before.roles[i][shapes[i]])
    assert np.array_equal(after.roles[:, :S], before.roles[:, :S]), "the arena keeps its roles"


def test_add_thruster():
    before, after = edited("add_thruster")
    b = before.state.bodies
    dynamic = (_shapes(before) & (b.inverse_mass != 0)).any(1)
    room = ~before.state.thrusters.active.all(1)
    added = after.state.thrusters.active.sum(1) - before.state.thrusters.active.sum(1)
    assert np.array_equal(added, (room & dynamic).astype(int))
    assert added.mean() > 0.5
    t = after.state.thrusters
    lv, sl = np.nonzero(t.active & ~before.state.thrusters.active)
    assert np.all(b.inverse_mass[lv, t.body_index[lv, sl]] != 0), "thrusters go on dynamic shapes"


def test_remove_thruster():
    before, after = edited("remove_thruster")
    had = before.state.thrusters.active.any(1)
    removed = before.state.thrusters.active.sum(1) - after.state.thrusters.active.sum(1)
    assert np.array_equal(removed, had.astype(int))


def test_toggle_fixed_flips_one_shape():
    before, after = edited("toggle_fixed")
    was = before.state.bodies.inverse_mass == 0
    now = after.state.bodies.inverse_mass == 0
    flipped = was != now
    assert np.all(flipped.sum(1) == 1) and not flipped[:, :S].any()
    assert np.all((after.state.bodies.inverse_inertia == 0)[flipped] == now[flipped])
    # A shape made dynamic gets its mass back from its density (1) and geometry.
    lv, body = np.nonzero(flipped & ~now)
    assert len(lv) > 0
    verts = after.state.polygon_vertices
    for i, k in zip(lv, body, strict=True):
        if k < P:
            half = np.abs(verts[i, k]).max(0)
            mass = 4 * half[0] * half[1]
        else:
            mass = np.pi * after.state.circle_radius[i, k - P] ** 2
        assert np.isclose(1 / after.state.bodies.inverse_mass[i, k], mass, rtol=1e-4)


def test_change_size_resizes_one_shape_and_its_anchors():
    before, after = edited("change_size")
    v0, v1 = before.state.polygon_vertices, after.state.polygon_vertices
    r0, r1 = before.state.circle_radius, after.state.circle_radius
    poly_changed = ~np.isclose(v0, v1, atol=1e-7).all(axis=(2, 3))
    circle_changed = ~np.isclose(r0, r1, atol=1e-7)
    changed = np.concatenate([poly_changed, circle_changed], axis=1)
    assert np.all(changed.sum(1) == 1)
    assert not changed[:, :S].any()
    lv, body = np.nonzero(changed)
    j0, j1 = before.state.joints, after.state.joints
    b = after.state.bodies
    for i, k in zip(lv, body, strict=True):
        if k < P:
            scale = np.abs(v1[i, k]).max(0) / np.abs(v0[i, k]).max(0)
            half = np.abs(v1[i, k]).max(0)
            assert np.all(half >= 0.05 - 1e-6) and np.all(half <= 0.7072)
            mass = 4 * half[0] * half[1]
        else:
            scale = np.full(2, r1[i, k - P] / r0[i, k - P])
            assert 0.1 - 1e-6 <= r1[i, k - P] <= 0.4 + 1e-6
            mass = np.pi * r1[i, k - P] ** 2
        if b.inverse_mass[i, k] != 0:
            assert np.isclose(1 / b.inverse_mass[i, k], mass, rtol=1e-4), "mass recomputed from density 1"
        on_a = j0.active[i] & (j0.a_index[i] == k)
        on_b = j0.active[i] & (j0.b_index[i] == k)
        np.testing.assert_allclose(j1.a_relative_pos[i][on_a], j0.a_relative_pos[i][on_a] * scale, rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(j1.b_relative_pos[i][on_b], j0.b_relative_pos[i][on_b] * scale, rtol=1e-4, atol=1e-6)
    assert np.all(after.state.bodies.velocity == 0) and np.all(after.state.bodies.angular_velocity == 0)


def _world_bounds(levels, i, bodies):
    pos, rot = levels.state.bodies.position[i], levels.state.bodies.rotation[i]
    low, high = np.full(2, np.inf), np.full(2, -np.inf)
    for k in bodies:
        if k < P:
            n = levels.state.polygon_n_vertices[i, k]
            local = levels.state.polygon_vertices[i, k, :n]
            c, s = np.cos(rot[k]), np.sin(rot[k])
            world = pos[k] + np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]], -1)
            low, high = np.minimum(low, world.min(0)), np.maximum(high, world.max(0))
        else:
            r = levels.state.circle_radius[i, k - P]
            low, high = np.minimum(low, pos[k] - r), np.maximum(high, pos[k] + r)
    return low, high


def test_change_location_moves_a_joint_group_inside_the_arena():
    before, after = edited("change_location")
    offset = after.state.bodies.position - before.state.bodies.position
    moved = np.abs(offset).max(-1) > 1e-6
    assert not moved[:, :S].any()
    assert moved.any(1).mean() > 0.9
    j = before.state.joints
    for i in np.nonzero(moved.any(1))[0]:
        group = np.nonzero(moved[i])[0]
        # One rigid translation for the whole group...
        np.testing.assert_allclose(offset[i, group], np.broadcast_to(offset[i, group[0]], (len(group), 2)), atol=1e-5)
        # ... and the group is closed under joints (a whole component).
        for slot in np.nonzero(j.active[i])[0]:
            assert (j.a_index[i, slot] in group) == (j.b_index[i, slot] in group)
        # Inside x in [0, 5], y in [0.4, 5] whenever the group fits in the arena.
        low, high = _world_bounds(after, i, group)
        size_low, size_high = _world_bounds(before, i, group)
        if np.all(size_high - size_low <= np.array([5.0, 4.6])):
            assert np.all(low >= np.array([0.0, 0.4]) - 1e-4) and np.all(high <= 5.0 + 1e-4), (i, low, high)
    assert np.array_equal(after.state.bodies.rotation, before.state.bodies.rotation)


def test_change_rotation_turns_one_shape_and_keeps_welds():
    before, after = edited("change_rotation")
    turn = after.state.bodies.rotation - before.state.bodies.rotation
    turned = np.abs(turn) > 1e-6
    assert not turned[:, :S].any()
    links = _joint_counts(before)
    # A shape without joints turns alone, by U(0, pi/2), and the settling leaves it alone.
    alone = turned.sum(1) == 1
    lv = np.nonzero(alone)[0]
    body = np.argmax(turned[lv], axis=1)
    loose = links[lv, body] == 0
    assert loose.sum() > 20
    assert np.all((turn[lv, body][loose] > 0) & (turn[lv, body][loose] <= np.pi / 2 + 1e-6))
    # Welds hold: the relative angle of every fixed joint stays at its reference.
    def weld_error(levels):
        j, rot = levels.state.joints, levels.state.bodies.rotation
        idx = np.arange(len(rot))[:, None]
        error = rot[idx, j.b_index] - rot[idx, j.a_index] - j.rotation
        return np.abs(np.where(j.active & j.is_fixed_joint, error, 0.0)).max()

    assert (before.state.joints.active & before.state.joints.is_fixed_joint).any()
    # Without the reference update a turned welded shape would be off by the turn itself (U(0, pi/2)); what is
    # left is the settling steps' small position-correction wobble.
    assert weld_error(before) < 1e-5 and weld_error(after) < 0.02


# ---------------------------------------------------------------------------------------------------------------
# Whole mutations

MUTATED_COUNT = 1000
MUTATED_VALIDATED = 250  # validate_scene is a host-side check at ~20 ms a level


@functools.cache
def parents_s():
    """MUTATED_COUNT S levels: the first of the shared S batch."""
    return first(host_levels("s"), MUTATED_COUNT)


@functools.cache
def mutated_s():
    before = parents_s()
    return before, to_host(mutate_levels(jax.random.key(5), before, SIZES["s"]))


def test_mutated_levels_are_valid():
    _, after = mutated_s()
    found = problems(after, MUTATED_VALIDATED)
    assert not found, found[:10]


def test_mutated_levels_keep_the_task_invariants():
    before, after = mutated_s()
    counts = summary(after, SIZES["s"])
    assert np.all(counts.green_all == 1) and np.all(counts.blue_all == 1)
    assert np.all(counts.red <= 1)
    assert np.all(after.roles[:, 0] == before.roles[:, 0]), "the floor keeps its role"
    changed = ~np.isclose(after.state.bodies.position, before.state.bodies.position).all(axis=(1, 2))
    changed |= (after.roles != before.roles).any(1)
    changed |= after.state.thrusters.active.sum(1) != before.state.thrusters.active.sum(1)
    changed |= ~np.isclose(after.state.bodies.rotation, before.state.bodies.rotation).all(1)
    changed |= ~np.isclose(after.state.bodies.inverse_mass, before.state.bodies.inverse_mass).all(1)
    assert changed.mean() > 0.95, "five edits almost always change a level"


def test_mutation_is_deterministic_and_zero_edits_copies_the_level_under_a_new_id():
    before, after = mutated_s()
    again = to_host(mutate_levels(jax.random.key(5), parents_s(), SIZES["s"]))
    for x, y in zip(jax.tree.leaves(again), jax.tree.leaves(after), strict=True):
        np.testing.assert_array_equal(x, y)
    level = jax.tree.map(lambda x: x[0], before)  # host arrays: the comparisons below run in numpy
    same = to_host(mutate_level(jax.random.key(0), level, SIZES["s"], MutationConfig(num_edits=0)))
    assert (same.level_id != level.level_id).any(), "a child is a new level"
    same = same.replace(level_id=level.level_id)
    assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(same), jax.tree.leaves(level), strict=True))
    ids = level_id_values(after.level_id)
    assert len(set(ids.tolist())) == len(ids) and not set(ids.tolist()) & set(level_id_values(before.level_id).tolist())


def test_operator_weights_follow_the_config_and_the_level():
    """Kinetix's gating: no shape additions without a free shape slot, no thruster addition without a free
    thruster slot, no removal without a thruster; configured weights otherwise."""
    levels = parents_s()
    weights = np.asarray(jax.jit(jax.vmap(lambda lv: edit_weights(lv, SIZES["s"], MutationConfig())))(levels))
    index = {n: i for i, n in enumerate(EDIT_NAMES)}
    has_thruster = np.asarray(levels.state.thrusters.active).any(1)  # S has one thruster slot
    assert np.all(weights[:, index["add_free_shape"]] == 0) and np.all(weights[:, index["add_connected_shape"]] == 0)
    assert np.array_equal(weights[:, index["add_thruster"]], np.where(has_thruster, 0.0, 1.0))
    assert np.array_equal(weights[:, index["remove_thruster"]], np.where(has_thruster, 1.0, 0.0))
    assert np.all(weights[:, index["toggle_fixed"]] == np.float32(0.1))
    assert np.all(weights[:, index["remove_joint"]] == 0) and np.all(weights[:, index["remove_shape"]] == 0)
    only = MutationConfig(**{f"{n}_weight": float(n == "swap_role") for n in EDIT_NAMES})
    assert only.weights == tuple(float(n == "swap_role") for n in EDIT_NAMES)
