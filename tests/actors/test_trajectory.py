"""The trajectory contract: every step records the id of the level it was played on, so results are credited by
level id even when the caller swaps the level batch while episodes are running; and every step carries the train
flag of its episode, which the episode takes from the level batch it started from."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from impulse.actors.rollout import rollout, start_rollout
from impulse.actors.trajectory import make_batch
from impulse.curriculum.results import level_results, results_to_host
from impulse.engine.env.actions import noop_action
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.level import level_id_values
from impulse.engine.levels.sets import load_level_set
from impulse.engine.physics.sizes import SIZE_S
from tests.support.quick_compile import quick_jit

SPEC = EnvSpec(sizes=SIZE_S, max_timesteps=12)
PARAMS = EnvParams()
NUM_ENVS = 4


def noop_policy(params, obs, key):
    """The all-zero action in every environment: episodes on these levels run to the time limit."""
    num = jax.tree.leaves(obs)[0].shape[0]
    action = jnp.broadcast_to(noop_action(SPEC), (num,) + noop_action(SPEC).shape)
    return action, jnp.zeros(num), jnp.zeros(num)


@functools.partial(quick_jit, static_argnums=3)
def play(carry, levels, train, num_steps):
    """One compiled rollout per (K, num_steps), shared by the tests: `train` is always an array."""
    return rollout(noop_policy, None, SPEC, PARAMS, carry, levels, num_steps, train)[:4]


CHUNK = 5  # every rollout in these tests is CHUNK steps of K = 2 levels: one compilation for the whole module


def play_for(carry, levels, train, num_steps):
    """`num_steps` (a multiple of CHUNK) steps as consecutive compiled rollouts, concatenated along time (on the
    host: numpy compiles nothing)."""
    parts = []
    for _ in range(num_steps // CHUNK):
        carry, steps, mask, stats = play(carry, levels, train, CHUNK)
        parts.append(jax.device_get((steps, mask, stats)))
    steps, mask, stats = jax.tree.map(lambda *xs: np.concatenate([np.atleast_1d(x) for x in xs]), *parts)
    return carry, steps, mask, jax.tree.map(np.sum, stats)


tally = quick_jit(level_results, static_argnames="rows")


def all_train(levels):
    return np.ones(levels.roles.shape[0], bool)


def ids(levels) -> set[int]:
    return set(level_id_values(np.asarray(levels.level_id)).tolist())


def test_swapping_the_level_batch_mid_episode_credits_the_level_played():
    _, first = load_level_set("handmade:s_easy_car_right,s_hop_over", SIZE_S)
    _, second = load_level_set("handmade:s_lander,s_catapult", SIZE_S)
    assert not ids(first) & ids(second)
    carry = start_rollout(SPEC, PARAMS, first, NUM_ENVS, jax.random.key(0))
    carry, before, _, _ = play(carry, first, all_train(first), CHUNK)  # 5 of 12 steps: no episode has ended yet
    assert not np.asarray(before.done).any()
    # Swap: the running episodes belong to the first batch; the next ones come from the second (25 steps: each
    # environment ends the carried-over episode and one more).
    carry, after, _, stats = play_for(carry, second, all_train(second), 5 * CHUNK)
    zeros = np.zeros(after.reward.shape, np.float32)
    results = results_to_host(tally(after.level_id, after.done, after.solved, after.episode_return, zeros, zeros, 0,
                                    rows=2 * NUM_ENVS + 4))
    credited = dict(zip(level_id_values(results["level_id"]).tolist(), results["episodes"].tolist(), strict=True))
    assert sum(credited.values()) == int(stats.episodes) == 2 * NUM_ENVS
    # The episodes that ended first (7 steps after the swap) were played on the first batch's levels.
    assert {k for k in credited if k in ids(first)} == ids(first)
    assert sum(v for k, v in credited.items() if k in ids(first)) == NUM_ENVS
    assert sum(v for k, v in credited.items() if k in ids(second)) == NUM_ENVS
    assert set(credited) <= ids(first) | ids(second)
    # The step that ends an episode records the level that episode started on, step after step.
    ended_first = level_id_values(np.asarray(after.level_id)[SPEC.max_timesteps - CHUNK - 1])
    assert set(ended_first.tolist()) == ids(first)


def test_a_batch_trains_on_every_step_unless_masked():
    _, levels = load_level_set("handmade:s_easy_car_right,s_hop_over", SIZE_S)
    carry = start_rollout(SPEC, PARAMS, levels, NUM_ENVS, jax.random.key(1))
    carry, steps, train_mask, _ = play(carry, levels, all_train(levels), CHUNK)
    batch = make_batch(steps, carry.obs, behaviour_version=7, actor_id=2, seq=9, train_mask=train_mask)
    assert batch.train_mask.shape == (CHUNK, NUM_ENVS) and bool(batch.train_mask.all())
    assert (int(batch.behaviour_version), int(batch.actor_id), int(batch.seq)) == (7, 2, 9)
    assert steps.level_id.shape == (CHUNK, NUM_ENVS, 2) and steps.level_id.dtype == jnp.uint32


def test_every_step_carries_the_train_flag_of_the_batch_its_episode_started_from():
    _, first = load_level_set("handmade:s_easy_car_right,s_hop_over", SIZE_S)
    _, second = load_level_set("handmade:s_lander,s_catapult", SIZE_S)
    first_train, second_train = np.array([True, False]), np.array([False, True])
    flag_of = {
        **dict(zip(level_id_values(np.asarray(first.level_id)).tolist(), first_train.tolist(), strict=True)),
        **dict(zip(level_id_values(np.asarray(second.level_id)).tolist(), second_train.tolist(), strict=True)),
    }
    carry = start_rollout(SPEC, PARAMS, first, NUM_ENVS, jax.random.key(2), first_train)
    assert np.asarray(carry.trains).tolist() == [True, False, True, False]  # environment i starts on level i % K
    # The same shapes as the test above (one compilation): 5 steps on the first batch, then the second batch while
    # the first batch's episodes are still running, long enough for every environment to start two more.
    carry, before, before_mask, _ = play(carry, first, first_train, CHUNK)
    carry, after, after_mask, _ = play_for(carry, second, second_train, 5 * CHUNK)
    for steps, mask in ((before, before_mask), (after, after_mask)):
        played = level_id_values(np.asarray(steps.level_id))
        expected = np.vectorize(flag_of.__getitem__)(played)
        np.testing.assert_array_equal(np.asarray(mask), expected)
    # Both flags occur, on both batches' levels, including episodes carried over from the first batch.
    played = level_id_values(np.asarray(after.level_id))
    mask = np.asarray(after_mask)
    assert set(played[:SPEC.max_timesteps - CHUNK].ravel().tolist()) == ids(first)
    assert set(played[-1].ravel().tolist()) <= ids(second)
    assert mask.any() and not mask.all()
    assert not mask[:SPEC.max_timesteps - CHUNK].all() and mask[:SPEC.max_timesteps - CHUNK].any()
