"""Batch-scored SFL in the curriculum service, over a real bus (zenoh on loopback; the test plays the learner): the
service follows the learner's weights, scores fresh candidates with the newest policy on a thread of its own, and
refills its buffer with the learnable ones, at the first weights and then every `sfl_refresh_updates` versions."""

from __future__ import annotations

import threading
import time

import jax
import numpy as np
import pytest

from impulse.actors.wire import weights_hash
from impulse.bus.session import Bus
from impulse.bus.stamp import Stamp
from impulse.bus.weights import encode_weights
from impulse.curriculum.methods import make_curriculum
from impulse.curriculum.service import CurriculumService
from impulse.curriculum.state import ORIGIN_REPLAY
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.status_display import curriculum_line
from impulse.engine.env.spec import env_from_config
from impulse.engine.pytree import tree_arrays
from impulse.learner.agent import make_agent
from impulse.learner.candidate_scorer import PolicyScorer
from impulse.learner.checkpoint import CURRICULUM, Checkpointer
from tests.support.launch_procs import QUICK_LAUNCH, free_port

RUN = "batch-sfl-test"
NONCE = "0123456789abcdef"
"""The instance nonce of the learner this test plays (`bus.keys.INSTANCE`)."""
CANDIDATES, ATTEMPTS, BUFFER, EVERY = 16, 2, 8, 4
BLOCK = 8  # candidates per scoring call: every scoring here runs as two blocks


def cycle_until(service: CurriculumService, condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}: {service.status()}"
        service.cycle()
        time.sleep(0.01)


def small_setup(*overrides: str):
    """The run config, env, agent (a small network: the tests are about the service), its parameters and the
    batch-scored SFL curriculum the tests share."""
    config = resolve_config(RunConfig, QUICK_LAUNCH, [
        f"bus.hub=tcp/127.0.0.1:{free_port()}", "env.levels=random", "curriculum=sfl", "curriculum.sfl_scoring=batch",
        f"curriculum.sfl_candidates={CANDIDATES}", f"curriculum.sfl_attempts={ATTEMPTS}",
        f"curriculum.sfl_refresh_updates={EVERY}", f"curriculum.buffer_size={BUFFER}", "curriculum.noop_filter=false",
        f"curriculum.sfl_score_block={BLOCK}",
        "ppo.num_envs=8", "network.width=16", "network.depth=1", *overrides])
    spec, env_params = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    curriculum = make_curriculum(config.curriculum, spec, env_params, config.ppo.num_envs)
    return config, env_params, agent, agent.init(jax.random.PRNGKey(0)), curriculum


def ask_levels(service: CurriculumService, asker: Bus) -> list[bytes]:
    """One level query, as an actor asks it, answered by the service cycling meanwhile: the batches it got."""
    replies: list[bytes] = []
    query = threading.Thread(target=lambda: replies.extend(asker.get(
        asker.keys.levels_sample, parameters=f"n={service.curriculum.batch_size}", timeout_s=10)))
    query.start()
    while query.is_alive():
        service.cycle()
        time.sleep(0.01)
    return replies


def test_the_service_refills_its_buffer_from_the_learners_policy(tmp_path) -> None:
    config, env_params, agent, params, curriculum = small_setup()
    with Bus(config.bus, RUN, "learner", "learner", listen=True) as learner, \
            Bus(config.bus, RUN, "curriculum", "curriculum") as bus, Checkpointer(tmp_path / "ckpt") as checkpoints:
        learner.declare_token(learner.keys.learner_instance(NONCE))  # followers adopt only this instance's weights
        weights = learner.latest_publisher(learner.keys.weights_policy)

        def publish(version: int) -> None:
            frame = encode_weights(Stamp(RUN, epoch=1, policy_version=version, nonce=NONCE), tree_arrays(params),
                                   weights_hash(params))
            weights.put(frame)

        scorer = PolicyScorer(bus, agent, env_params, ATTEMPTS)
        service = CurriculumService(curriculum, bus, checkpoints, "", lambda current, assignments: current,
                                    item=CURRICULUM, scorer=scorer)
        service.start()
        assert not np.asarray(service.state.buffer.filled).any()
        # Training starts on a scored buffer: until the first refill, level queries are refused (actors ask again).
        assert ask_levels(service, learner) == [] and service.requests_held == 1
        assert service.status()["filling"] and "holding level requests" in curriculum_line(service.status())
        publish(0)
        cycle_until(service, lambda: service.refills == 1, 300, "the first refill, from version 0")
        assert len(ask_levels(service, learner)) == 1 and not service.status()["filling"]
        assert "| refills 1 (v0, " in curriculum_line(service.status())
        assert service.status()["scored_candidates"] == [CANDIDATES, CANDIDATES]
        filled = np.asarray(service.state.buffer.filled)
        refill = service.status()["last_refill"]
        learnable, solved = round(refill["learnable"] * CANDIDATES), round(refill["solved"] * CANDIDATES)
        assert filled.sum() == min(solved, BUFFER), "the most learnable kept; never-solved candidates never"
        # Two attempts: a learnable level was solved once (p = 0.5), scored p (1 - p) + 0.001 p, ahead of the
        # always-solved ones (0.001).
        expected = [0.2505] * min(learnable, BUFFER) + [0.001] * (min(solved, BUFFER) - min(learnable, BUFFER))
        np.testing.assert_allclose(np.sort(np.asarray(service.state.buffer.score)[filled])[::-1], expected,
                                   rtol=1e-5)
        if filled.any():
            _, batch = curriculum.sample(service.state, jax.random.PRNGKey(1))
            assert (np.asarray(batch.origin) == ORIGIN_REPLAY).sum() == round(0.5 * curriculum.batch_size)

        for version in range(1, EVERY):  # within the same refresh period: no new scoring
            publish(version)
            cycle_until(service, lambda v=version: scorer.follow.version == v, 30, f"weights version {version}")
            assert service.refills == 1 and service.status()["scoring"] is False
        publish(EVERY)
        cycle_until(service, lambda: service.refills == 2, 120, "the second refill")
        assert service.status()["last_refill"]["version"] == EVERY
        service.save()
        assert checkpoints.restore({CURRICULUM: service.state}).counters["refills"] == 2


class GatedScorer:
    """A real `PolicyScorer` whose scorings wait until the test lets them finish."""

    def __init__(self, scorer: PolicyScorer) -> None:
        self.scorer, self.gate = scorer, threading.Event()

    def policy(self):
        return self.scorer.policy()

    def counts(self):
        return self.scorer.counts()

    def solve_rates(self, params, levels, key):
        assert self.gate.wait(60), "the test never let the scoring finish"
        return self.scorer.solve_rates(params, levels, key)


@pytest.mark.parametrize("hold", [False, True])
def test_level_requests_during_a_later_scoring_are_held_only_when_asked(tmp_path, hold: bool) -> None:
    hold_override = f"curriculum.sfl_hold_while_scoring={str(hold).lower()}"
    config, env_params, agent, params, curriculum = small_setup(hold_override)
    with Bus(config.bus, RUN, "learner", "learner", listen=True) as learner, \
            Bus(config.bus, RUN, "curriculum", "curriculum") as bus, Checkpointer(tmp_path / "ckpt") as checkpoints:
        learner.declare_token(learner.keys.learner_instance(NONCE))  # followers adopt only this instance's weights
        weights = learner.latest_publisher(learner.keys.weights_policy)
        scorer = GatedScorer(PolicyScorer(bus, agent, env_params, ATTEMPTS))
        service = CurriculumService(curriculum, bus, checkpoints, "", lambda current, assignments: current,
                                    item=CURRICULUM, scorer=scorer)
        service.start()
        for version in (0, EVERY):
            stamp = Stamp(RUN, epoch=1, policy_version=version, nonce=NONCE)
            weights.put(encode_weights(stamp, tree_arrays(params), weights_hash(params)))
            cycle_until(service, lambda: service.status()["scoring"], 30, f"the scoring of version {version}")
            # held at its first block by the gate: the line counts what is scored of how many
            assert f"scoring 0/{CANDIDATES}" in curriculum_line(service.status())
            answered = ask_levels(service, learner)
            if version == 0 or hold:
                assert answered == [], "held: the first scoring, or every scoring with sfl_hold_while_scoring"
            else:
                assert len(answered) == 1, "answered from the current buffer while the scoring runs"
            scorer.gate.set()
            cycle_until(service, lambda v=version: service.refills == 1 + v // EVERY, 120, "the refill")
            scorer.gate.clear()
        assert service.requests_held == (2 if hold else 1)
        assert len(ask_levels(service, learner)) == 1
