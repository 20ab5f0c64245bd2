"""Batching: vmapped steps equal single steps, and 300 random scenes run 500 steps without NaN."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.physics import (
    add_circle,
    add_rectangle,
    add_revolute_joint,
    add_thruster,
    validate_scene,
)
from tests.support.physics_random_scenes import build_scenes, draw_actions, draw_parameters
from tests.support.physics_sim import (
    CHUNK,
    NUM_ACTIONS,
    PARAMS,
    SIZES,
    arena_scene,
    non_finite_leaves,
    run,
    run_batch,
    stack,
    take,
    zero_gravity,
)


def _four_scenes():
    """Four different scenes of the shared size: contacts, a motorised joint, a thruster, a bounce."""
    s1 = arena_scene()
    s1, _ = add_rectangle(s1, (2.5, 0.65), 0.5, 0.5)
    s1, _ = add_rectangle(s1, (2.6, 1.3), 0.4, 0.4, rotation=0.3)
    s2 = arena_scene()
    s2, anchor = add_rectangle(s2, (2.5, 3.0), 0.1, 0.1, fixed=True)
    s2, arm = add_rectangle(s2, (3.0, 3.0), 1.0, 0.1)
    s2, _ = add_revolute_joint(s2, anchor, arm, (0.0, 0.0), (-0.5, 0.0), motor_on=True)
    s3 = zero_gravity(arena_scene())
    s3, body = add_rectangle(s3, (1.5, 2.5), 0.6, 0.3, rotation=0.5)
    s3, _ = add_thruster(s3, body, (0.2, 0.1), rotation=0.2, power=1.0)
    s3, _ = add_circle(s3, (2.5, 2.5), 0.3, velocity=(-1.0, 0.0))
    s4 = arena_scene()
    s4, _ = add_circle(s4, (1.0, 0.8), 0.2, velocity=(1.0, -2.0), restitution=0.8)
    s4, _ = add_circle(s4, (1.2, 1.5), 0.25, angular_velocity=2.0)
    actions = np.zeros((4, CHUNK, NUM_ACTIONS), np.float32)
    actions[1, :, 0] = 0.7  # motor of scene 2
    actions[2, :, 2] = 1.0  # thruster of scene 3
    return [s1, s2, s3, s4], actions


NUM_SCENES = 300
NUM_STEPS = 500
LIMIT = PARAMS.clip_position


def test_vmapped_step_equals_single_step():
    """The four scenes, each repeated to fill a batch of NUM_SCENES (so the vmapped run is the compiled `run_batch`
    the random scenes below use), against each scene run alone: every copy equals its single run."""
    scenes, actions = _four_scenes()
    copies = NUM_SCENES // len(scenes)
    assert copies * len(scenes) == NUM_SCENES
    batch = jax.tree.map(lambda x: np.concatenate([np.asarray(x)] * copies), stack(scenes))
    final, batched = run_batch(batch, PARAMS, jnp.asarray(np.concatenate([actions] * copies)), SIZES)
    batched = [np.asarray(r) for r in batched]  # [NUM_SCENES, CHUNK, ...]; scene i at rows i, i + 4, i + 8, ...
    for i, scene in enumerate(scenes):
        alone, records = run(scene, PARAMS, jnp.asarray(actions[i]), SIZES)
        # Same arithmetic in a different compiled layout: results may differ by float32 rounding, amplified a
        # little by 20 steps of contact solving; 1e-5 is far below any physical difference.
        for t in range(CHUNK):
            for k, name in enumerate(("position", "rotation", "velocity", "angular_velocity")):
                want = np.asarray(records[k])[t]
                np.testing.assert_allclose(
                    batched[k][i :: len(scenes), t],
                    np.broadcast_to(want, (copies, *want.shape)),
                    atol=1e-5,
                    rtol=1e-5,
                    err_msg=f"scene {i}, step {t}, bodies.{name}",
                )
            touching = np.asarray(records[4])[t]
            np.testing.assert_array_equal(
                batched[4][i :: len(scenes), t], np.broadcast_to(touching, (copies, *touching.shape))
            )
        # Every leaf of the final state, joints, thrusters and contact cache included.
        for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(final), jax.tree.leaves(alone)):
            b = np.asarray(b)
            np.testing.assert_allclose(
                np.asarray(a)[i :: len(scenes)],
                np.broadcast_to(b, (copies, *b.shape)),
                atol=1e-5,
                rtol=1e-5,
                err_msg=f"scene {i}: {jax.tree_util.keystr(path)}",
            )


class RandomRun(dict):
    """The fixture's results; a short repr keeps failure reports readable."""

    def __repr__(self) -> str:
        return f"RandomRun({NUM_SCENES} scenes x {NUM_STEPS} steps)"


@pytest.fixture(scope="module")
def random_run():
    """Build 300 random scenes in one vmapped call, then run them 500 steps (25 calls of CHUNK steps)."""
    start = time.perf_counter()
    scenes = build_scenes(draw_parameters(NUM_SCENES, seed=20240611))
    jax.block_until_ready(scenes)
    built = time.perf_counter()
    actions = draw_actions(NUM_SCENES, NUM_STEPS, seed=7)
    active = np.asarray(scenes.bodies.active)
    first_non_finite = np.full(NUM_SCENES, -1)
    first_at_clamp = np.full(NUM_SCENES, -1)  # first step a body sat on the clamp box (|x| or |y| = 15)
    worst_position = np.zeros(NUM_SCENES)
    state = scenes
    first_chunk = None
    for c in range(NUM_STEPS // CHUNK):
        state, records = run_batch(state, PARAMS, jnp.asarray(actions[:, c * CHUNK : (c + 1) * CHUNK]), SIZES)
        position, rotation, velocity, angular_velocity = (np.asarray(r) for r in records[:4])
        finite = (
            np.isfinite(position).all(axis=(2, 3))
            & np.isfinite(velocity).all(axis=(2, 3))
            & np.isfinite(rotation).all(axis=2)
            & np.isfinite(angular_velocity).all(axis=2)
        )
        new = (~finite).any(axis=1) & (first_non_finite < 0)
        first_non_finite[new] = c * CHUNK + np.argmax(~finite[new], axis=1)
        reach = np.where(active[:, None, :, None] & np.isfinite(position), np.abs(position), 0.0)
        worst_position = np.maximum(worst_position, reach.max(axis=(1, 2, 3)))
        clamped = (reach >= LIMIT - 1e-3).any(axis=(2, 3))
        new = clamped.any(axis=1) & (first_at_clamp < 0)
        first_at_clamp[new] = c * CHUNK + np.argmax(clamped[new], axis=1)
        if first_chunk is None:
            first_chunk = time.perf_counter()
    done = time.perf_counter()
    print(
        f"\nrandom scenes: build {built - start:.1f} s (with compile), first {CHUNK} steps {first_chunk - built:.1f} s "
        f"(with compile), other {NUM_STEPS - CHUNK} steps x {NUM_SCENES} scenes {done - first_chunk:.1f} s"
    )
    return RandomRun(
        scenes=scenes,
        final=state,
        first_non_finite=first_non_finite,
        first_at_clamp=first_at_clamp,
        worst_position=worst_position,
    )


def test_random_scenes_are_valid(random_run):
    scenes = random_run["scenes"]
    active = np.asarray(scenes.bodies.active)
    # The generator must produce varied scenes: on average several bodies, joints and thrusters each.
    assert active[:, SIZES.num_static_polygons :].sum(axis=1).mean() > 4
    assert np.asarray(scenes.joints.active).sum() > NUM_SCENES
    assert np.asarray(scenes.thrusters.active).sum() > NUM_SCENES
    problems = {}
    host = jax.tree.map(np.asarray, scenes)  # validate_scene on numpy arrays: a host check, no device round trips
    for i in range(NUM_SCENES):
        found = validate_scene(take(host, i))
        if found:
            problems[i] = found
    assert not problems, f"{len(problems)} invalid scenes, e.g. {dict(list(problems.items())[:3])}"


def test_random_scenes_stay_finite(random_run):
    first, clamp = random_run["first_non_finite"], random_run["first_at_clamp"]
    bad = np.flatnonzero(first >= 0)
    examples = ", ".join(
        f"scene {i} at step {first[i]} (on the clamp box from step {clamp[i]})" for i in bad[:8]
    )
    assert bad.size == 0, f"{bad.size} of {NUM_SCENES} scenes produced NaN/inf: {examples}"
    assert not non_finite_leaves(random_run["final"])


def test_random_scenes_stay_in_clamp_box(random_run):
    worst = random_run["worst_position"]
    # Positions are clamped to +-clip_position after every step; checked on every recorded step of every active
    # body (NaN values are the other test's business).
    assert worst.max() <= LIMIT + 1e-5, f"scene {int(np.argmax(worst))} reached |x| or |y| = {worst.max()}"
