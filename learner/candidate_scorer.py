"""The policy the curriculum service scores candidate levels with, in a distributed run with batch-scored SFL
(`curriculum.sfl_scoring=batch`).

Kinetix's SFL rebuilds its buffer from fresh levels that the current policy plays a few times each. The fused
trainer does that inside its jitted step (`learner.fused.FusedTrainer.refill_curriculum`); in a distributed run
the curriculum service owns the buffer but not the policy, so it is given this scorer: it follows the learner's
weights as the actors and the evaluator do (`actors.follow.LearnerFollower`) and plays levels with them through
the same function the fused trainer uses (`learner.evaluate.solve_rates`). It implements the curriculum service's
`CandidateScorer`; the service calls `policy` from its loop and `solve_rates` from its scoring thread.
"""

from __future__ import annotations

from typing import Any

import jax

from impulse.actors.follow import LearnerFollower
from impulse.bus.session import Bus
from impulse.engine.env.spec import EnvParams
from impulse.engine.levels.level import Level
from impulse.learner.agent import Agent
from impulse.learner.evaluate import solve_rates


class PolicyScorer:
    """The learner's newest policy, and candidate levels' solve rates under it (`attempts` episodes each)."""

    def __init__(self, bus: Bus, agent: Agent, env_params: EnvParams, attempts: int):
        self.follow = LearnerFollower(bus, jax.eval_shape(agent.init, jax.random.PRNGKey(0)))
        self._solve_rates = jax.jit(
            lambda params, levels, key: solve_rates(agent, params, env_params, levels, key, attempts))

    def policy(self) -> tuple[int, Any] | None:
        """(policy version, parameters) of the newest weights adopted, or None before the first."""
        self.follow.poll()
        if self.follow.params is None:
            return None
        return self.follow.version, self.follow.params

    def counts(self) -> dict[str, int]:
        """The weights follower's counts (adopted, repeated, overwritten in its inbox, re-synced, learners seen)."""
        return dict(self.follow.counts)

    def solve_rates(self, params: Any, levels: Level, key: jax.Array) -> jax.Array:
        """The fraction of episodes solved on each of `levels` [C] by the policy `params` (blocks until done)."""
        return jax.block_until_ready(self._solve_rates(params, levels, key))
