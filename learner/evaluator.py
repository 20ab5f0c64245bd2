"""The evaluator process: it follows the learner's weights (`actors.follow.LearnerFollower`) and scores the newest
policy on level sets (`learner.scoring`, the function `impulse eval` uses, Kinetix's protocol) while the run
trains, in a process and on a device of its own, so the learner never waits for it.

One cycle (driven by the shared run loop): adopt the newest weights; when the policy is `evaluator.every_updates`
versions past the last one scored (or of a new learner epoch), score it and publish the scores on
`evaluator/results/<id>` (`bus.evaluations`): per level and per group. The learner writes them to metrics.jsonl
(the `eval/...` columns, the same as `impulse train`'s periodic evaluation writes), the launcher's status display
shows them, and Rerun plots them. Scoring takes a while; the versions that pass meanwhile are not scored: the
evaluator always scores the newest, and counts the evaluation points it skipped. It stops when the learner has
finished the run, as the actors do.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import jax

from impulse.actors.follow import LearnerFollower
from impulse.bus.evaluations import encode_evaluation
from impulse.bus.keys import EVALUATOR
from impulse.bus.service import CycleReport, Progress
from impulse.bus.session import Bus
from impulse.bus.status import StatusPublisher
from impulse.engine.env.spec import EnvParams
from impulse.learner.agent import Agent
from impulse.learner.config import EvaluatorConfig
from impulse.learner.scoring import LevelSets, Scored, evaluating_phase, evaluation_columns, score_policy

log = logging.getLogger("impulse.evaluator")

EVALUATOR_ID = EVALUATOR
CHUNK_LEVELS = 8
"""Levels the evaluator plays at a time (`score_policy`'s `chunk_levels`): its status says after each chunk how many
levels of the set are scored, so the launcher's display shows a long evaluation advance (42 levels x 20 attempts
take minutes on a CPU). A chunk of 8 levels x 20 attempts is still 160 episodes side by side."""


class EvaluatorService:
    """The evaluator's state and its run-loop `cycle` (see the module docstring)."""

    def __init__(self, config: EvaluatorConfig, *, seed: int, status_every_s: float, bus: Bus, agent: Agent,
                 env_params: EnvParams, sets: LevelSets, ident: str = EVALUATOR_ID):
        self.config = config
        self.seed = seed
        self.bus = bus
        self.agent, self.env_params, self.sets = agent, env_params, sets
        self.follow = LearnerFollower(bus, jax.eval_shape(agent.init, jax.random.PRNGKey(0)))
        self._results = bus.publisher(bus.keys.evaluation(ident))
        self._status = StatusPublisher(bus, status_every_s)
        self.scored_at: tuple[int, int] | None = None
        """(learner epoch, policy version) of the last policy scored."""
        self.latest: Scored | None = None
        self.evaluations = 0
        self.skipped = 0
        self.last_seconds = 0.0
        self.scoring: tuple[int, float] | None = None
        """(policy version, wall-clock start) of the scoring under way, which holds the loop: its status says so
        before it starts and after each chunk of levels, and the launcher's display counts its seconds."""
        self.levels_scored = 0
        """Levels of the scoring under way scored so far."""

    def _due(self) -> bool:
        if self.follow.params is None:
            return False
        if self.scored_at is None or self.follow.epoch != self.scored_at[0]:
            return True
        return self.follow.version >= self.scored_at[1] + self.config.every_updates

    def cycle(self) -> CycleReport | None:
        if self._status.due():
            self._status.publish(self.status())
        self.follow.poll()
        if not self._due():
            return None
        epoch, version = self.follow.epoch, self.follow.version
        skipped = 0
        if self.scored_at is not None and epoch == self.scored_at[0]:
            skipped = max(0, (version - self.scored_at[1]) // self.config.every_updates - 1)
        start = time.perf_counter()
        self.scoring, self.levels_scored = (version, time.time()), 0
        self._status.publish(self.status())
        try:
            scored = score_policy(self.agent, self.follow.params, self.env_params, self.sets,
                                  jax.random.PRNGKey(self.seed + 1 + version), self.config.attempts,
                                  on_level=self._scored_level, chunk_levels=CHUNK_LEVELS)
        finally:
            self.scoring = None
        self.last_seconds = time.perf_counter() - start
        self.bus.stamp.acting_for(epoch, version)
        self._results.put(encode_evaluation(self.bus.stamp, scored.table, scored.groups, skipped))
        self.scored_at, self.latest = (epoch, version), scored
        self.evaluations += 1
        self.skipped += skipped
        log.info("policy version %d (epoch %d): mean solve rate %.0f%%%s in %.1f s%s", version, epoch,
                 100 * scored.mean, "".join(f", {g} {r:.0%}" for g, r in scored.groups.items()), self.last_seconds,
                 f"; {skipped} evaluation points skipped while scoring" if skipped else "")
        metrics = {"policy_version": float(version), "seconds": self.last_seconds,
                   **evaluation_columns(scored.table, scored.groups, version)}
        return CycleReport(metrics=metrics)

    def status(self) -> dict[str, Any]:
        latest = self.latest
        return {
            "role": self.bus.role,
            "name": EVALUATOR_ID,
            "policy_version": self.follow.version,
            "scored_version": None if self.scored_at is None else self.scored_at[1],
            "evaluations": self.evaluations,
            "skipped": self.skipped,
            "seconds": self.last_seconds,
            "mean": None if latest is None else latest.mean,
            "groups": {} if latest is None else latest.groups,
            "levels": len(self.sets.names),
            "rejected": self.bus.rejects.counts(),
            **self.follow.counts,
            **self._phase(),
        }

    def _scored_level(self, done: int, total: int, name: str, solve_rate: float) -> None:
        """After each chunk of levels, the status says how many are scored (`score_policy`'s `on_level`)."""
        self.levels_scored = done
        if done == total or done % CHUNK_LEVELS == 0:
            self._status.publish(self.status())

    def _phase(self) -> dict[str, Any]:
        """The blocking phase, while it scores: which policy, how many levels of how many are scored, since when."""
        if self.scoring is None:
            return {}
        version, since = self.scoring
        return {"phase": evaluating_phase(len(self.sets.names), self.config.attempts, self.levels_scored),
                "phase_since": since, "scoring_version": version}

    def start(self) -> None:
        """Nothing to prepare: it scores once weights arrive."""

    def progress(self) -> Progress:
        return Progress()

    def save(self, summary: dict[str, float]) -> None:
        """Nothing to keep: the scores are the learner's to write down."""

    def finished(self) -> bool:
        if self.follow.learner_finished:
            log.info("the learner finished the run: the evaluator stops")
            return True
        return False

    def close(self) -> None:
        """Tell whoever watches where it got to."""
        self._status.publish(self.status())
