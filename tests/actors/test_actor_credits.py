"""An actor's credits and weights, driven cycle by cycle over a real bus (the test plays the learner): it never has
more batches in flight than its credits, an acknowledgement frees one at once, and batches nobody acknowledges are
written off after `actors.credit_timeout_s` instead of stalling the actor for ever, or after longer when the
learner's pace says they may still be queued; newer weights are adopted, while a replayed older frame and a frame
with a flipped bit are refused and counted, and the version never goes back."""

from __future__ import annotations

import time
from functools import partial

import jax
import pytest

from impulse.actors.follow import PACE_WINDOW
from impulse.actors.levels import LocalLevels
from impulse.actors.process import Actor
from impulse.actors.wire import weights_hash
from impulse.bus.credits import encode_credit
from impulse.bus.session import Bus
from impulse.bus.stamp import Stamp
from impulse.bus.weights import encode_weights
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.engine.env.spec import env_from_config
from impulse.engine.pytree import tree_arrays
from impulse.learner.agent import make_agent
from impulse.learner.curriculum_inputs import batch_level_results
from tests.support.launch_procs import QUICK_LAUNCH, TINY_BATCH, free_port

pytestmark = pytest.mark.heavy

RUN = "credit-test"
NONCE = "0123456789abcdef"
"""The instance nonce of the learner this test plays (`bus.keys.INSTANCE`)."""
TIMEOUT_S = 1.5
SLOW_PACE_S = 1.0


def cycle_until(actor: Actor, condition, timeout_s: float, what: str) -> float:
    start = time.monotonic()
    while not condition():
        assert time.monotonic() - start < timeout_s, f"timed out waiting for {what}: {actor.counts}"
        actor.cycle()
    return time.monotonic() - start


def test_credits_bound_in_flight_batches_and_unacknowledged_ones_are_written_off():
    port = free_port()
    config = resolve_config(RunConfig, QUICK_LAUNCH, [
        f"bus.hub=tcp/127.0.0.1:{port}", f"actors.credit_timeout_s={TIMEOUT_S}", *TINY_BATCH])
    spec, env_params = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    params = agent.init(jax.random.PRNGKey(0))
    with Bus(config.bus, RUN, "learner", "learner", listen=True) as learner:
        learner.stamp.acting_for(epoch=1, policy_version=5)
        learner.declare_token(learner.keys.learner_instance(NONCE))  # followers adopt only this instance's weights
        weights = learner.latest_publisher(learner.keys.weights_policy)

        def weights_frame(version: int) -> bytearray:
            stamp = Stamp(RUN, epoch=1, policy_version=version, nonce=NONCE)
            return bytearray(encode_weights(stamp, tree_arrays(params), weights_hash(params)))

        weights.put(weights_frame(5))
        trajectories = learner.inbox(learner.keys.traj_all, 16)
        with Bus(config.bus, RUN, "actor", "actor-0") as bus:
            actor = Actor(config.actors, num_envs=config.ppo.num_envs, num_steps=config.ppo.num_steps,
                          seed=config.seed, index=0, bus=bus, agent=agent, env_params=env_params,
                          levels=LocalLevels(config.env, spec.sizes),
                          level_results=partial(batch_level_results, agent, config.ppo))
            actor.start()
            cycle_until(actor, lambda: actor.counts["sent"] == 1, 120, "the first batch")
            assert actor.version == 5 and actor.in_flight == 1
            for _ in range(20):
                actor.cycle()
            assert actor.counts["sent"] == 1, "no credit left: the actor waits"

            waited = cycle_until(actor, lambda: actor.counts["sent"] == 2, 30, "the write-off")
            assert actor.ledger.written_off == 1 and waited >= TIMEOUT_S * 0.5

            credit = learner.publisher(learner.keys.credit("actor-0"))
            assert learner.wait_matching(credit, 10)
            credit.put(encode_credit(learner.stamp, actor.incarnation, 2))
            waited = cycle_until(actor, lambda: actor.counts["sent"] == 3, 30, "the acknowledged credit")
            assert waited < TIMEOUT_S and actor.ledger.written_off == 1, "freed by the acknowledgement"

            credit.put(encode_credit(learner.stamp, actor.incarnation + 1, 3))
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                actor.cycle()
            assert actor.in_flight == 1, "an acknowledgement for another incarnation frees nothing"

            # Weights: newer ones are adopted; a replay of older ones and a corrupted copy are refused.
            def refusals(reason: str) -> int:
                return bus.rejects.counts().get(reason, 0)

            weights.put(weights_frame(7))
            cycle_until(actor, lambda: actor.version == 7, 30, "weights version 7")
            weights.put(weights_frame(6))
            cycle_until(actor, lambda: refusals("stale") == 1, 30, "the replayed version 6 to be refused")
            flipped = weights_frame(8)
            flipped[len(flipped) // 2] ^= 0x04
            weights.put(flipped)
            cycle_until(actor, lambda: refusals("digest") == 1, 30, "the corrupted version 8 to be refused")
            weights.put(weights_frame(7))
            cycle_until(actor, lambda: actor.follow.counts["weights_repeated"] >= 1, 30,
                        "version 7 again to be ignored")
            assert actor.version == 7 and actor.follow.counts["weights_adopted"] == 2
            received = trajectories.poll()
            assert [len(r.payload) > 0 for r in received] == [True] * 3

            # A learner slower than the timeout: versions come SLOW_PACE_S apart, so a batch may wait (every
            # actor's credits + its own) x SLOW_PACE_S in its queue, and the actor waits that long, not TIMEOUT_S.
            for version in range(9, 9 + PACE_WINDOW):
                weights.put(weights_frame(version))
                cycle_until(actor, lambda v=version: actor.version == v, 30, f"weights version {version}")
                pause_until = time.monotonic() + SLOW_PACE_S
                while time.monotonic() < pause_until:
                    actor.cycle()
            assert 0.9 * SLOW_PACE_S <= actor.follow.seconds_per_version < 2 * SLOW_PACE_S
            queue = config.actors.num_actors * config.actors.credits + 1
            assert actor.credit_deadline_s() == pytest.approx(queue * actor.follow.seconds_per_version)
            assert actor.credit_deadline_s() > 1.5 * TIMEOUT_S
            credit.put(encode_credit(learner.stamp, actor.incarnation, actor.seq))
            sent = actor.counts["sent"]
            cycle_until(actor, lambda: actor.counts["sent"] == sent + 1, 30, "the batch after the acknowledgement")
            written_off = actor.ledger.written_off
            waited = cycle_until(actor, lambda: actor.ledger.written_off > written_off, 60, "the slow write-off")
            assert waited >= 0.8 * actor.credit_deadline_s() > TIMEOUT_S, "waited for the slow learner's pace"
