"""The trajectory contract: every step records the id of the level it was played on, so results are credited by
level id even when the caller swaps the level batch while episodes are running."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from actors.rollout import RolloutCarry, rollout
from actors.trajectory import level_results, make_batch
from engine.env.actions import noop_action
from engine.env.env import reset_batch
from engine.env.spec import EnvParams, EnvSpec
from engine.levels.level import level_id_values
from engine.levels.sets import load_level_set
from engine.physics.sizes import SIZE_S

SPEC = EnvSpec(sizes=SIZE_S, max_timesteps=12)
PARAMS = EnvParams()
NUM_ENVS = 4


def noop_policy(params, obs, key):
    """The all-zero action in every environment: episodes on these levels run to the time limit."""
    num = jax.tree.leaves(obs)[0].shape[0]
    action = jnp.broadcast_to(noop_action(SPEC), (num,) + noop_action(SPEC).shape)
    return action, jnp.zeros(num), jnp.zeros(num)


@functools.partial(jax.jit, static_argnums=2)
def play(carry, levels, num_steps):
    return rollout(noop_policy, None, SPEC, PARAMS, carry, levels, num_steps)


def ids(levels) -> set[int]:
    return set(level_id_values(np.asarray(levels.level_id)).tolist())


def test_swapping_the_level_batch_mid_episode_credits_the_level_played():
    _, first = load_level_set("handmade:s_easy_car_right,s_hop_over", SIZE_S)
    _, second = load_level_set("handmade:s_lander,s_catapult", SIZE_S)
    assert not ids(first) & ids(second)
    obs, state = reset_batch(SPEC, PARAMS, first, NUM_ENVS)
    carry = RolloutCarry(state, obs, jax.random.key(0))
    carry, before, _ = play(carry, first, 5)  # 5 of 12 steps: no episode has ended yet
    assert not bool(before.done.any())
    # Swap: the running episodes belong to the first batch; the next ones come from the second.
    carry, after, stats = play(carry, second, 2 * SPEC.max_timesteps)
    results = level_results(after)
    credited = dict(zip(results.level_id.tolist(), results.episodes.tolist(), strict=True))
    assert sum(credited.values()) == int(stats.episodes) == 2 * NUM_ENVS
    # The episodes that ended first (7 steps after the swap) were played on the first batch's levels.
    assert {k for k in credited if k in ids(first)} == ids(first)
    assert sum(v for k, v in credited.items() if k in ids(first)) == NUM_ENVS
    assert sum(v for k, v in credited.items() if k in ids(second)) == NUM_ENVS
    assert set(credited) <= ids(first) | ids(second)
    # The step that ends an episode records the level that episode started on, step after step.
    ended_first = level_id_values(np.asarray(after.level_id)[SPEC.max_timesteps - 5 - 1])
    assert set(ended_first.tolist()) == ids(first)


def test_a_batch_trains_on_every_step_unless_masked():
    _, levels = load_level_set("handmade:s_easy_car_right", SIZE_S)
    obs, state = reset_batch(SPEC, PARAMS, levels, NUM_ENVS)
    carry, steps, _ = play(RolloutCarry(state, obs, jax.random.key(1)), levels, 3)
    batch = make_batch(steps, carry.obs, behaviour_version=7, actor_id=2, seq=9)
    assert batch.train_mask.shape == (3, NUM_ENVS) and bool(batch.train_mask.all())
    assert (int(batch.behaviour_version), int(batch.actor_id), int(batch.seq)) == (7, 2, 9)
    assert steps.level_id.shape == (3, NUM_ENVS, 2) and steps.level_id.dtype == jnp.uint32
