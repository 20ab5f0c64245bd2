"""Random level generation: validity, the task invariants, Kinetix's distribution, variety, purity, and physics
sanity of the generated scenes."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.benchmarks.kernel_check import trajectories
from impulse.engine.levels.generator import GeneratorConfig, sample_random_level, sample_random_levels
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_RED
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.params import SimParams
from tests.support.level_samples import SIZES, STAT_COUNTS, host_levels, problems, random_levels, summary, take

# Kinetix's measured statistics of unfiltered random levels (reference digest, table 9.4): sample size, then the
# mean per level of each count. "controllable" is the fraction of levels with a motor-on joint or a thruster.
TABLE_9_4 = {
    "s": (256, dict(polygons=1.00, circles=2.00, joints=0.71, fixed_joints=0.0, motor_on=0.56, thrusters=0.65,
                    fixated=0.00, red=0.08, neutral=0.94, controllable=0.922)),
    "m": (256, dict(polygons=1.94, circles=2.40, joints=1.37, fixed_joints=0.0, motor_on=1.12, thrusters=0.95,
                    fixated=1.34, red=0.21, neutral=2.15, controllable=0.992)),
    "l": (128, dict(polygons=6.21, circles=3.20, joints=3.89, fixed_joints=1.05, motor_on=2.37, thrusters=0.89,
                    fixated=2.98, red=0.73, neutral=6.70, controllable=1.0)),
}
# The same counts from larger samples, measured by running kinetix-env 3.0.2's `sample_kinetix_level` (jax 0.10.2,
# CPU, the benchmarks' reference venv): 4,096 S levels, 2,048 M levels, 2 x 1,024 L levels with different seeds.
MEASURED_KINETIX = {
    "s": (4096, dict(polygons=1.0, circles=2.0, joints=0.6726, fixed_joints=0.0, motor_on=0.5339, thrusters=0.6672,
                     fixated=0.0, red=0.0791, controllable=0.9326)),
    "m": (2048, dict(polygons=1.9062, circles=2.4458, joints=1.3052, fixed_joints=0.0, motor_on=1.0391,
                     thrusters=0.9551, fixated=1.4033, red=0.2319, controllable=0.978)),
    "l": (2048, dict(polygons=6.0503, circles=3.2563, joints=3.8174, fixed_joints=0.9619, motor_on=2.2979,
                     thrusters=0.9624, fixated=2.9575, red=0.7002, controllable=0.9966)),
}
FLOOR_ROLE_PROBS = (0.9, 0.0, 0.02, 0.08)
# Levels run through validate_scene per size (it is a host-side check at 20 to 45 ms a level).
VALIDATED = {"s": 300, "m": 100, "l": 100}
# The NaN check: batches of random S levels stepped with zero actions, shaped as test_physics_kernel's comparison.
NAN_CHECK_BATCH, NAN_CHECK_BATCHES, NAN_CHECK_STEPS = 16, 7, 120


def _within(ours: np.ndarray, reference_mean: float, reference_n: int, rounding: float) -> tuple[bool, float]:
    """Whether our sample mean matches a reference mean from reference_n levels: both are means of the same
    distribution if the generator is right, so their difference has standard error sd * sqrt(1/n + 1/n_ref)
    (sd estimated from our larger sample). Four standard errors make a false alarm ~6e-5 per comparison; the
    reference's own rounding is added on top."""
    sd = float(np.std(ours, ddof=1))
    tolerance = 4.0 * sd * math.sqrt(1.0 / len(ours) + 1.0 / reference_n) + rounding
    return abs(float(np.mean(ours)) - reference_mean) <= tolerance, tolerance


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_generated_levels_are_valid(size):
    levels = host_levels(size)
    found = problems(levels, VALIDATED[size])
    assert not found, found[:10]


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_every_level_has_one_green_one_blue_and_at_most_one_red(size):
    levels = host_levels(size)
    counts = summary(levels, SIZES[size])
    assert np.all(counts.green_all == 1), "every level has exactly one green shape (or a green floor)"
    assert np.all(counts.blue_all == 1), "every level has exactly one blue shape or a blue floor"
    floor_blue = counts.floor == ROLE_BLUE
    assert np.array_equal(counts.blue_shapes == 0, floor_blue), "a blue shape is missing only when the floor is blue"
    assert np.all(counts.red <= 1)
    assert np.all(counts.red[counts.floor == ROLE_RED] == 0), "no red shape when the floor is red"
    assert np.all(levels.roles[:, 1:4] == 0), "walls and ceiling stay neutral"
    assert floor_blue.any(), "with thousands of levels some floors are blue (p = 0.02)"


def test_floor_role_frequencies():
    floors = np.concatenate([summary(host_levels(s), SIZES[s]).floor for s in SIZES])
    n = len(floors)
    for role, p in enumerate(FLOOR_ROLE_PROBS):
        freq = np.mean(floors == role)
        tolerance = 4.0 * math.sqrt(p * (1 - p) / n)
        assert abs(freq - p) <= tolerance, (role, freq, p, tolerance)
    assert not np.any(floors == ROLE_GREEN), "Kinetix never makes the floor green"


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_counts_match_kinetix(size):
    counts = summary(host_levels(size), SIZES[size])
    failures = []
    for name, (n_ref, means), rounding in (("table 9.4", TABLE_9_4[size], 0.005),
                                            ("measured", MEASURED_KINETIX[size], 0.0)):
        for stat, mean in means.items():
            ours = getattr(counts, stat).astype(np.float64)
            ok, tolerance = _within(ours, mean, n_ref, rounding)
            if not ok:
                failures.append(f"{name} {stat}: ours {ours.mean():.3f} vs {mean} (tolerance {tolerance:.3f})")
    assert not failures, failures


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_joint_rules(size):
    levels, sizes = host_levels(size), SIZES[size]
    P = sizes.num_polygons
    j = levels.state.joints
    level, slot = np.nonzero(j.active)
    a, b = j.a_index[level, slot], j.b_index[level, slot]
    assert np.all(a != b)
    # At most two joints per rectangle and one per circle; no circle-circle links.
    counts = np.zeros(levels.roles.shape, np.int64)
    np.add.at(counts, (level, a), 1)
    np.add.at(counts, (level, b), 1)
    assert counts[:, :P].max() <= 2 and counts[:, P:].max() <= 1
    assert not np.any((a >= P) & (b >= P))
    assert np.all(a >= sizes.num_static_polygons) and np.all(b >= sizes.num_static_polygons), "never on the arena"
    fixed = j.is_fixed_joint[level, slot]
    if size in ("s", "m"):
        assert not fixed.any(), "S and M never get fixed joints"
    else:
        assert fixed.any() and (~fixed).any()
    revolute = ~fixed
    rect_rect = (a < P) & (b < P)
    limits = j.motor_has_joint_limits[level, slot]
    assert not np.any(limits & ~(rect_rect & revolute)), "joint limits only on rectangle-rectangle revolute joints"
    lo, hi = j.min_rotation[level, slot][limits], j.max_rotation[level, slot][limits]
    assert np.all((-np.pi <= lo) & (lo <= 0) & (0 <= hi) & (hi <= np.pi))
    power, speed = j.motor_power[level, slot], j.motor_speed[level, slot]
    assert np.allclose(power[revolute & ~rect_rect], 1.0), "wheels (a circle in the joint) get motor power 1"
    assert np.all((power[revolute & rect_rect] >= 1.0) & (power[revolute & rect_rect] <= 3.0))
    assert np.all((speed[revolute] >= 0.4) & (speed[revolute] <= 3.0))
    assert not np.any(j.motor_on[level, slot] & fixed)
    motor_on_rate = j.motor_on[level, slot][revolute].mean()
    assert abs(motor_on_rate - 0.8) < 4 * math.sqrt(0.16 / revolute.sum())
    # Roles: no green-blue link; red only next to neutral shapes.
    ra, rb = levels.roles[level, a], levels.roles[level, b]
    pair = {tuple(sorted(x)) for x in zip(ra.tolist(), rb.tolist(), strict=True)}
    assert (1, 2) not in pair
    assert all(r == 0 or other == 0 for r, other in pair if 3 in (r, other))
    # The two anchors coincide in the world.
    pos, rot = levels.state.bodies.position, levels.state.bodies.rotation

    def world(body, rel):
        c, s = np.cos(rot[level, body]), np.sin(rot[level, body])
        return pos[level, body] + np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]], -1)

    assert np.allclose(world(a, j.a_relative_pos[level, slot]), world(b, j.b_relative_pos[level, slot]), atol=1e-4)
    assert np.all((levels.motor_bindings >= 0) & (levels.motor_bindings < 4))


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_shape_and_thruster_rules(size):
    levels, sizes = host_levels(size), SIZES[size]
    P, S = sizes.num_polygons, sizes.num_static_polygons
    bodies = levels.state.bodies
    shapes = bodies.active.copy()
    shapes[:, :S] = False
    # Dimensions: rectangle half-extents in [0.05, 2 * 0.354]; radii in [0.1, 0.4].
    verts = levels.state.polygon_vertices
    half = np.abs(verts).max(axis=2)[shapes[:, :P]]
    assert half.min() >= 0.05 - 1e-6 and half.max() <= 2 * 1.0 / (2 * math.sqrt(2)) + 1e-6
    radius = levels.state.circle_radius[shapes[:, P:]]
    assert radius.min() >= 0.1 - 1e-6 and radius.max() <= 0.4 + 1e-6
    assert np.all(levels.state.polygon_n_vertices[shapes[:, :P]] == 4)
    # Mass in Jax2D's convention at density 1: rectangles m = 4 hx hy, I = m (hx^2 + hy^2) / 3; circles m = pi r^2,
    # I = m r^2 / 4.
    dynamic = shapes & (bodies.inverse_mass > 0)
    hx, hy = np.abs(verts[..., 0]).max(-1), np.abs(verts[..., 1]).max(-1)
    m_rect = 4 * hx * hy
    rect = dynamic[:, :P]
    assert np.allclose(bodies.inverse_mass[:, :P][rect], 1 / m_rect[rect], rtol=1e-4)
    assert np.allclose(bodies.inverse_inertia[:, :P][rect], 3 / (m_rect * (hx**2 + hy**2))[rect], rtol=1e-4)
    r = levels.state.circle_radius
    circ = dynamic[:, P:]
    m_circle = np.pi * r**2
    assert np.allclose(bodies.inverse_mass[:, P:][circ], 1 / m_circle[circ], rtol=1e-4)
    assert np.allclose(bodies.inverse_inertia[:, P:][circ], 4 / (m_circle * r**2)[circ], rtol=1e-4)
    assert np.all(bodies.inverse_inertia[shapes & (bodies.inverse_mass == 0)] == 0)
    # Fixation: never in S; green and blue shapes never both fixed.
    fixed = shapes & (bodies.inverse_mass == 0)
    if size == "s":
        assert not fixed.any()
    green_fixed = (fixed & (levels.roles == ROLE_GREEN)).any(1)
    blue_fixed = (fixed & (levels.roles == ROLE_BLUE)).any(1)
    assert not np.any(green_fixed & blue_fixed)
    # Free (unjointed) dynamic shapes lie inside the arena: x in [0, 5], y in [0.4, 5].
    j = levels.state.joints
    jointed = np.zeros(shapes.shape, bool)
    lv, sl = np.nonzero(j.active)
    jointed[lv, j.a_index[lv, sl]] = True
    jointed[lv, j.b_index[lv, sl]] = True
    free = dynamic & ~jointed
    reach = np.concatenate([np.hypot(hx, hy), r], axis=1)
    x, y = bodies.position[..., 0], bodies.position[..., 1]
    eps = 1e-4
    assert np.all((x - reach >= -eps)[free]) and np.all((x + reach <= 5 + eps)[free])
    assert np.all((y - reach >= 0.4 - eps)[free]) and np.all((y + reach <= 5 + eps)[free])
    # Thrusters: on dynamic shapes, inside them, thrust/mass = 2 * U(0.5, 2).
    t = levels.state.thrusters
    lv, sl = np.nonzero(t.active)
    body = t.body_index[lv, sl]
    assert np.all(dynamic[lv, body])
    accel = t.power[lv, sl] * bodies.inverse_mass[lv, body]
    assert accel.min() >= 1.0 - 1e-4 and accel.max() <= 4.0 + 1e-4
    rel = t.relative_position[lv, sl]
    on_rect = body < P
    assert np.all(np.abs(rel[on_rect, 0]) <= hx[lv, np.minimum(body, P - 1)][on_rect] + 1e-5)
    assert np.all(np.abs(rel[on_rect, 1]) <= hy[lv, np.minimum(body, P - 1)][on_rect] + 1e-5)
    assert np.all(np.hypot(*rel[~on_rect].T) <= r[lv, np.maximum(body - P, 0)][~on_rect] + 1e-5)
    assert np.all((levels.thruster_bindings >= 0) & (levels.thruster_bindings < 2))


def test_levels_vary_and_slots_are_shuffled():
    levels = host_levels("m")
    green = levels.roles == ROLE_GREEN
    has_green_shape = green[:, 4:].any(1)
    green_index = np.argmax(green, axis=1)[has_green_shape]
    green_pos = levels.state.bodies.position[has_green_shape, green_index]
    assert np.std(green_pos[:, 0]) > 0.5 and np.std(green_pos[:, 1]) > 0.3
    assert len(np.unique(np.round(green_pos, 5), axis=0)) == len(green_pos), "no two levels share the green position"
    # Green sits in different slots (the final shuffle), among both polygons and circles.
    assert len(np.unique(green_index)) >= 4
    assert (green_index < SIZES["m"].num_polygons).any() and (green_index >= SIZES["m"].num_polygons).any()


def test_sampling_is_deterministic_and_seeds_differ():
    again = sample_random_levels(jax.random.key(0), STAT_COUNTS["s"], SIZES["s"])
    first = random_levels("s")
    assert all(jax.tree.leaves(jax.tree.map(lambda x, y: np.array_equal(np.asarray(x), np.asarray(y)), first, again)))
    other = host_levels("s", STAT_COUNTS["s"], 1)
    assert not np.allclose(other.state.bodies.position, host_levels("s").state.bodies.position)


def test_single_level_equals_its_batch_entry():
    """The sampler is a pure function of its key: jitting one level gives the vmapped batch's entry."""
    sizes = SIZES["s"]
    keys = jax.random.split(jax.random.key(0), STAT_COUNTS["s"])
    single = jax.jit(sample_random_level, static_argnums=(1,))
    batch = host_levels("s")
    for i in (0, 1, 7):
        one = jax.tree.map(np.asarray, single(keys[i], sizes))
        expected = take(batch, i)
        for x, y in zip(jax.tree.leaves(one), jax.tree.leaves(expected), strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-5)


def test_config_is_honoured():
    """A neutral floor always, no green/blue swap and the opposite-side rule always on: green then lies in the
    left half and blue in the right half (they are the two free shapes placed first and never moved)."""
    config = GeneratorConfig(floor_role_probs=(1.0, 0.0, 0.0, 0.0), swap_green_blue_chance=0.0,
                             opposite_side_chance=1.0)
    levels = jax.tree.map(np.asarray, sample_random_levels(jax.random.key(3), 256, SIZES["s"], config))
    assert np.all(levels.roles[:, 0] == 0)
    x = levels.state.bodies.position[..., 0]
    assert np.all(x[levels.roles == ROLE_GREEN] <= 2.5) and np.all(x[levels.roles == ROLE_BLUE] >= 2.5)


def test_generated_levels_simulate_without_nan():
    """112 random S levels (7 batches of 16) stepped 120 times with zero actions stay finite: every body position
    after every step. The stepping is `kernel_check.trajectories` on the XLA step with the batch shape
    test_physics_kernel compares (16 S scenes, 120 steps), so the two tests share one compiled program."""
    sizes = SIZES["s"]
    levels = host_levels("s")
    actions = jnp.zeros((NAN_CHECK_STEPS, NAN_CHECK_BATCH, sizes.num_joints + sizes.num_thrusters), jnp.float32)
    for b in range(NAN_CHECK_BATCHES):
        batch = slice(b * NAN_CHECK_BATCH, (b + 1) * NAN_CHECK_BATCH)
        states = jax.tree.map(lambda x, batch=batch: x[batch], levels.state)
        positions = np.asarray(trajectories(states, SimParams(), actions, sizes, SolverOptions(backend="xla")))
        assert np.isfinite(positions).all(), f"batch {b}: non-finite positions"
        # Something moved: dynamic shapes fall or are driven by joints under gravity.
        moved = np.abs(positions[-1] - states.bodies.position).max(axis=-1) > 1e-3
        assert moved.any(axis=1).all(), f"batch {b}: levels {np.flatnonzero(~moved.any(axis=1))} never moved"
