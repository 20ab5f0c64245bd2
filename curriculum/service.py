"""The curriculum service: the authority on levels in a distributed run.

It owns the curriculum state (`curriculum.methods`) and talks to the rest of the run only over the bus:

- `levels/sample` (queryable): an actor asks for its next batch of B levels and gets a LEVELS frame (the levels,
  whether each is trained on, where each came from);
- `levels/results/*` (subscription): actors' per-level results, checked (`curriculum.wire`), then applied with
  the jitted `update`; malformed or impossible results are refused, counted by reason and never crash it;
- `curriculum/knobs` (queryable): read the live knobs, or change them (`{"set": ["replay_prob=0.8", ...]}`),
  validated by the run's config system (a function the caller passes in) and applied at the next sample;
- `curriculum/inspect` (queryable): buffer statistics, the top levels and, on request, their scenes;
- `curriculum/inject` (queryable): a level a person sends in (`{"level": <a Kinetix level file's object>}`, from
  `impulse curriculum inject` or the studio), loaded at the run's size and checked as `impulse levels validate`
  does, then put into the buffer (`Curriculum.insert`); refused with the reason otherwise. Only the operator role
  may ask (`bus.router.access_rules`);
- `metrics/curriculum/0`: a status line with buffer statistics for `impulse launch`'s display.

New random levels pass the no-op filter on a thread of their own, `curriculum.levels_ahead` batches ahead of the
requests (`curriculum.ahead`), so a request waits only for the cheap rest of `sample`.

With batch-scored SFL (`curriculum.sfl_scoring=batch`) results do not score levels: every `sfl_refresh_updates`
policy versions (and once the first weights arrive) the service draws `sfl_candidates` fresh levels, has the
learner's newest policy play each `sfl_attempts` times (a `CandidateScorer` the caller passes in, which follows
the learner's weights) and refills its buffer with the most learnable (`Curriculum.refill`). The scoring runs on a
thread of its own, in blocks of `sfl_score_block` candidates whose count the status line shows
(`scored_candidates`), so level queries are answered from the current buffer meanwhile; the refill is applied in
`cycle`, like everything else that changes the state. Until the first refill, level queries are refused with the
reason (actors wait and ask again), so that training starts on a scored buffer, as the fused trainer's does,
rather than on fresh levels alone; with `sfl_hold_while_scoring` during every scoring.

Its whole state, knobs included, is checkpointed with orbax as the `curriculum` item (through a checkpointer the
caller passes in), so a restarted service resumes with every buffered and staged level. Work happens in the
caller's thread in `cycle` (it is a `bus.service.Service`, driven by the run loop like every process), except the
candidate scoring above; nothing is done in zenoh callbacks.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import secrets
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from impulse.bus.codec import Rejected
from impulse.bus.control import control_reply, encode_refusal, encode_report
from impulse.bus.inbox import IncomingQuery
from impulse.bus.keys import CURRICULUM
from impulse.bus.levels import decode_level_results, encode_level_batch, level_query_expired
from impulse.bus.roles import CURRICULUM_ROLE
from impulse.bus.service import CycleReport, Progress
from impulse.bus.session import Bus
from impulse.bus.status import StatusPublisher
from impulse.curriculum.ahead import LevelMaker
from impulse.curriculum.config import LIVE_KNOBS, CurriculumConfig
from impulse.curriculum.methods import Curriculum
from impulse.curriculum.results import empty_results
from impulse.curriculum.state import CurriculumState, config_with_knobs
from impulse.curriculum.stats import (
    buffer_summary,
    inspect_report,
    json_scalar,
    live_knob_values,
    top_levels,
)
from impulse.curriculum.wire import ResultsError, checked_results, level_batch_arrays, results_chunks
from impulse.engine.levels.kinetix_json import load_level_document
from impulse.engine.levels.level import Level, level_id_values
from impulse.engine.pytree import tree_arrays

log = logging.getLogger(__name__)

CURRICULUM_ID = CURRICULUM
RESULTS_PER_ROUND = 8
"""Result messages applied between two looks at the level requests (a few `update` calls: one actor's message
fills half of one), so that a request never waits behind a flood of results."""
RESULT_ROUNDS = 8
"""Rounds of results per cycle at most, so that results never starve the knob, inspect and inject queries."""
SCORING_JOIN_S = 10.0
"""How long `close` waits for a candidate scoring under way (the launcher gives the service 20 s to stop)."""

KnobResolver = Callable[[CurriculumConfig, list[str]], CurriculumConfig]
"""Applies `key=value` assignments to a config, raising ValueError with the config system's message."""


class RestoredCheckpoint(Protocol):
    """What a checkpoint store's `restore` returns (`learner.checkpoint.Restored` fits)."""

    @property
    def items(self) -> dict[str, Any]: ...

    @property
    def counters(self) -> dict[str, Any]: ...

    @property
    def step(self) -> int: ...


class CheckpointStore(Protocol):
    """What the service needs of a checkpointer (`learner.checkpoint.Checkpointer` fits)."""

    def save(self, step: int, items: dict[str, Any], counters: dict[str, Any], config_toml: str) -> None: ...

    def restore(self, templates: dict[str, Any], step: int | None = None) -> RestoredCheckpoint:
        """The newest intact checkpoint (corrupt newer ones are moved aside) or checkpoint `step`."""
        ...

    def latest_step(self) -> int | None: ...


class CandidateScorer(Protocol):
    """What batch-scored SFL needs in a distributed run (`learner.candidate_scorer.PolicyScorer` fits): the
    learner's newest policy, and candidate levels played with it."""

    def policy(self) -> tuple[int, Any] | None:
        """(policy version, parameters) of the newest weights, or None before the first (called from `cycle`)."""
        ...

    def solve_rates(self, params: Any, levels: Level, key: jax.Array) -> jax.Array:
        """The fraction of episodes solved on each of `levels` by `params` (called from the scoring thread)."""
        ...

    def counts(self) -> dict[str, int]:
        """What following the learner's weights adopted and dropped, for the status line (`dropped_...` fields
        reach the learner's metrics.jsonl)."""
        ...


class Refill(NamedTuple):
    """A finished scoring of candidates, waiting for `cycle` to refill the buffer with it."""

    candidates: Level
    solve_rate: jax.Array
    policy_version: int
    seconds: float


class CurriculumService:
    """One curriculum process (see the module docstring). `cycle` does whatever is waiting and reports what it did;
    `save` checkpoints. Its bus entities live as long as the bus session."""

    def __init__(
        self,
        curriculum: Curriculum,
        bus: Bus,
        checkpoints: CheckpointStore,
        config_toml: str,
        resolve_knobs: KnobResolver,
        *,
        item: str = "curriculum",
        seed: int = 0,
        resume: bool = False,
        status_every_s: float = 1.0,
        queue: int = 256,
        scorer: CandidateScorer | None = None,
    ):
        """`scorer`: the policy that scores candidates, required by batch-scored SFL and unused otherwise."""
        if curriculum.batch_scored and scorer is None:
            raise ValueError("batch-scored SFL needs a scorer: the policy that plays the candidate levels")
        self.curriculum = curriculum
        self.bus = bus
        self.checkpoints = checkpoints
        self.config_toml = config_toml
        self.resolve_knobs = resolve_knobs
        self.item = item
        self.rows = 2 * curriculum.batch_size  # one actor window touches at most E + K = 2B levels
        self._key = jax.random.PRNGKey(seed)
        self._init = jax.jit(curriculum.init)
        self._sample = jax.jit(curriculum.sample)
        self._update = jax.jit(curriculum.update)
        self.state: CurriculumState = self._init(jax.random.fold_in(self._key, 0))
        self.samples = 0
        self.result_messages = 0
        self.knob_changes = 0
        self.refills = 0
        self.requests_held = 0
        """Level queries refused while the buffer waited for its first scoring (batch-scored SFL)."""
        self.expired_queries = 0
        """Level queries refused because they waited half their asker's stated wait in the queue
        (`bus.levels.level_query_expired`)."""
        self.injected = 0
        self.policy_version = 0
        self.incarnation = secrets.randbits(31)
        """Drawn at start: tells this process's status counters from a predecessor's (`bus.status.DropTotals`)."""
        self._saved_step: int | None = None
        if resume and checkpoints.latest_step() is not None:
            self._restore()
        keys = bus.keys
        self._results = bus.inbox(keys.levels_results_all, queue)
        self._sample_queries = bus.queryable(keys.levels_sample, queue)
        self._knob_queries = bus.queryable(keys.curriculum_knobs, 16)
        self._inspect_queries = bus.queryable(keys.curriculum_inspect, 16)
        self._inject_queries = bus.queryable(keys.curriculum_inject, 16)
        self._insert = jax.jit(curriculum.insert)
        self._status = StatusPublisher(bus, status_every_s)
        self.scorer = scorer if curriculum.batch_scored else None
        self._scoring: threading.Thread | None = None
        self._scored: Refill | BaseException | None = None  # what the scoring thread left for `cycle`
        self._scoring_version = -1  # the policy version the newest scoring started from
        self.scored_candidates = (0, 0)
        """(candidates scored, candidates) of the newest scoring: it plays `sfl_score_block` of them per call."""
        self._last_refill: dict[str, float] = {}
        if self.scorer is not None:
            config = curriculum.config
            self._candidates = jax.jit(lambda key: curriculum.new_levels(key, config.sfl_candidates))
            self._refill = jax.jit(curriculum.refill)
        self.maker: LevelMaker | None = None
        if curriculum.config.noop_filter and curriculum.config.levels_ahead > 0:
            b = curriculum.batch_size
            self.maker = LevelMaker(jax.jit(lambda key: curriculum.new_levels(key, b)),
                                    jax.jit(lambda key: curriculum.random_levels(key, b)),
                                    jax.random.fold_in(jax.random.fold_in(self._key, 2), self.samples),
                                    curriculum.config.levels_ahead)

    # -- lifecycle -------------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Compile sample and update before serving, so the first actor's query does not wait for XLA (a query
        times out after a few seconds)."""
        start = time.perf_counter()
        fresh, filtered = None, False
        if self.maker is not None:
            self.maker.start()
            fresh, filtered = self.maker.take()
        state, _ = self._sample(self.state, self._key, fresh)
        if fresh is not None:
            self.maker.give_back(fresh, filtered)
        self._update(state, empty_results(self.rows))
        log.info("curriculum %s compiled in %.1f s", self.curriculum.method, time.perf_counter() - start)

    def _restore(self) -> None:
        template = jax.eval_shape(self.curriculum.init, self._key)
        restored = self.checkpoints.restore({self.item: template})
        counters = restored.counters
        self.state = restored.items[self.item]
        self.samples = int(counters.get("samples", 0))
        self.result_messages = int(counters.get("result_messages", 0))
        self.policy_version = int(counters.get("policy_version", 0))
        # Restored too, so that the checkpoint step (their sum with the above) never goes back after a restart.
        self.knob_changes = int(counters.get("knob_changes", 0))
        self.refills = int(counters.get("refills", 0))
        self.injected = int(counters.get("injected", 0))
        self._saved_step = restored.step
        log.info("curriculum resumed from checkpoint %s: %d levels buffered, %d staged, %d samples served",
                 self._saved_step, int(np.asarray(self.state.buffer.filled).sum()),
                 int(np.asarray(self.state.staging.staged).sum()), self.samples)

    @property
    def step(self) -> int:
        """Checkpoint step: everything the service has done (monotonic across restarts)."""
        return self.samples + self.result_messages + self.knob_changes + self.refills + self.injected

    def save(self, summary: dict[str, float] | None = None) -> None:
        """Checkpoint the whole state, unless nothing happened since the last checkpoint (`summary`, the run loop's
        metrics window, is not kept: the curriculum has its own statistics)."""
        if self.step == self._saved_step:
            return
        counters = {"samples": self.samples, "result_messages": self.result_messages,
                    "policy_version": self.policy_version, "knob_changes": self.knob_changes,
                    "refills": self.refills, "injected": self.injected}
        self.checkpoints.save(self.step, {self.item: self.state}, counters, self.config_toml)
        self._saved_step = self.step

    @property
    def config(self) -> CurriculumConfig:
        """The config with the live knob values."""
        return config_with_knobs(self.curriculum.config, self.state.knobs)

    # -- the run loop's service -------------------------------------------------------------------------------------

    def progress(self) -> Progress:
        """No goal: the service runs until it is stopped. Its checkpoint cadence counts result messages applied."""
        return Progress()

    def finished(self) -> bool:
        return False

    @property
    def scoring_under_way(self) -> bool:
        """Whether a candidate scoring's thread is still inside XLA (after `close`: it outlived the wait)."""
        return self._scoring is not None and self._scoring.is_alive()

    def close(self) -> None:
        """Stop making levels ahead; checkpoint what happened since the last checkpoint (samples and knob changes
        too); give a candidate scoring under way a little time to finish (a process that exits while a thread is
        inside XLA aborts at the interpreter's teardown: `impulse curriculum serve` then ends without one)."""
        if self.maker is not None:
            self.maker.close()
        try:
            self.save()
        finally:  # a save that fails (a full disk) still lets the scoring thread finish first
            if self.scoring_under_way:
                log.info("waiting up to %.0f s for the candidate scoring under way", SCORING_JOIN_S)
                self._scoring.join(SCORING_JOIN_S)

    def cycle(self) -> CycleReport | None:
        """Apply waiting results (or a finished candidate scoring), answer waiting queries; what was done
        (`updates`: result messages applied and refills, which drive the checkpoint cadence), or None if nothing
        was."""
        # Level requests first and between rounds of results, as actors wait on them.
        served = self._answer_samples()
        applied = 0
        for _ in range(RESULT_ROUNDS):
            taken, accepted = self._apply_results()
            applied += accepted
            served += self._answer_samples()
            if taken < RESULTS_PER_ROUND:
                break
        applied += self._refresh() if self.scorer is not None else 0
        for query in self._knob_queries.poll():
            self._answer_knobs(query)
        for query in self._inspect_queries.poll():
            self._answer_inspect(query)
        for query in self._inject_queries.poll():
            self._answer_inject(query)
        if self._status.due():
            self._status.publish(self.status())
        if not applied and not served:
            return None
        return CycleReport(updates=applied, metrics={"result_messages": float(applied),
                                                     "samples_served": float(served)})

    def _apply_results(self) -> tuple[int, int]:
        """Apply the result messages waiting (RESULTS_PER_ROUND at most), in the order they came, packed into as few
        `update` calls as their rows fit in; returns how many messages were taken, and how many of them applied
        (the rest were refused and counted)."""
        accepted = []
        waiting = self._results.poll(RESULTS_PER_ROUND)
        for received in waiting:
            try:
                message = decode_level_results(received.payload, self.bus.keys.run)
                accepted.append(checked_results(message))
            except Rejected as err:
                self.bus.rejects.record(err.reason, received.key, err.detail)
                continue
            except ResultsError as err:
                self.bus.rejects.record("schema", received.key, str(err))
                continue
            self.policy_version = max(self.policy_version, message.policy_version)
            self.result_messages += 1
        for chunk in results_chunks(accepted, self.rows):
            self.state = self._update(self.state, chunk)
        return len(waiting), len(accepted)

    # -- batch-scored SFL ---------------------------------------------------------------------------------------------

    def _refresh(self) -> int:
        """Refill the buffer from a finished scoring (1), or start a scoring when the learner's policy has moved
        `sfl_refresh_updates` versions past the last one scored, or is the first one seen (0)."""
        if self._scoring is not None:
            if self._scoring.is_alive():
                return 0
            self._scoring, scored = None, self._scored
            if isinstance(scored, BaseException):
                raise RuntimeError("scoring the candidate levels failed") from scored
            assert scored is not None
            self.state = self._refill(self.state, scored.candidates, scored.solve_rate,
                                      jnp.asarray(scored.policy_version, jnp.int32))
            self.refills += 1
            rates = np.asarray(scored.solve_rate)
            self._last_refill = {"version": scored.policy_version, "seconds": round(scored.seconds, 2),
                                 "learnable": float(((rates > 0) & (rates < 1)).mean()),
                                 "solved": float((rates > 0).mean())}
            log.info("SFL refill %d from policy v%d: %d candidates scored in %.1f s, %.0f%% learnable, buffer %.0f%% "
                     "full", self.refills, scored.policy_version, rates.size, scored.seconds,
                     100 * self._last_refill["learnable"], 100 * float(np.asarray(self.state.buffer.filled).mean()))
            return 1
        held = self.scorer.policy()
        if held is None:
            return 0
        version, params = held
        self.policy_version = max(self.policy_version, version)
        every = self.curriculum.config.sfl_refresh_updates
        if self._scoring_version >= 0 and version // every <= self._scoring_version // every:
            return 0
        self._scoring_version = version
        key = jax.random.fold_in(jax.random.fold_in(self._key, 1), version)
        self.scored_candidates = (0, self.curriculum.config.sfl_candidates)
        self._scoring = threading.Thread(target=self._score, args=(params, key, version), daemon=True,
                                         name="sfl-scoring")
        self._scoring.start()
        return 0

    def _score(self, params: Any, key: jax.Array, version: int) -> None:
        """The scoring thread: fresh candidates, played by `params`; the outcome is left for `_refresh`."""
        try:
            started = time.perf_counter()
            level_key, play_key = jax.random.split(key)
            candidates = self._candidates(level_key)
            total = self.curriculum.config.sfl_candidates
            block = min(self.curriculum.config.sfl_score_block, total)
            rates = []
            for first in range(0, total, block):
                self.scored_candidates = (first, total)  # read by status() on the service's thread
                part = jax.tree.map(lambda leaf, first=first: leaf[first:first + block], candidates)
                part_key = play_key if block == total else jax.random.fold_in(play_key, first)
                rates.append(self.scorer.solve_rates(params, part, part_key))
            self.scored_candidates = (total, total)
            self._scored = Refill(candidates, jnp.concatenate(rates), version, time.perf_counter() - started)
        except BaseException as err:  # noqa: BLE001 - handed to the service's own thread, which raises it
            self._scored = err

    def _answer_samples(self) -> int:
        return sum(self._answer_sample(query) for query in self._sample_queries.poll())

    @property
    def filling(self) -> bool:
        """Batch-scored SFL before its first refill, or while any scoring runs with `sfl_hold_while_scoring`:
        level queries wait for a scored buffer."""
        if self.scorer is None:
            return False
        return self.refills == 0 or (self.curriculum.config.sfl_hold_while_scoring and self._scoring is not None)

    def _answer_sample(self, query: IncomingQuery) -> int:
        wanted = query.parameters.get("n")
        if wanted is not None and wanted != str(self.curriculum.batch_size):
            query.reply_error(f"this curriculum serves batches of {self.curriculum.batch_size} levels, not {wanted}")
            return 0
        if level_query_expired(query.parameters, query.waited_s):
            self.expired_queries += 1
            query.reply_error(f"the query waited {query.waited_s:.1f} s for the service, too long to serve")
            return 0
        if self.filling:
            self.requests_held += 1
            query.reply_error("the level buffer is being filled: a candidate scoring is under way")
            return 0
        key = jax.random.fold_in(self._key, self.samples + 1)
        fresh, filtered = self.maker.take() if self.maker is not None else (None, False)
        new_batches = self.state.counters.new_batches
        self.state, batch = self._sample(self.state, key, fresh)
        if fresh is not None and int(self.state.counters.new_batches) == int(new_batches):
            self.maker.give_back(fresh, filtered)  # a replayed batch: the new levels wait for the next request
        self.samples += 1
        query.reply(encode_level_batch(self.bus.stamp, level_batch_arrays(batch)))
        return 1

    # -- control -------------------------------------------------------------------------------------------------------

    def live_knobs(self) -> dict[str, Any]:
        return live_knob_values(self.curriculum.config, self.state)

    def set_knobs(self, assignments: list[str]) -> dict[str, list[Any]]:
        """Apply `key=value` assignments (keys relative to the curriculum section); returns {name: [old, new]}
        for what changed. Raises ValueError with a message for a person, and changes nothing then."""
        if not isinstance(assignments, list) or not all(isinstance(a, str) for a in assignments):
            raise ValueError('"set" must be a list of "key=value" strings')
        current = self.config
        updated = self.resolve_knobs(current, assignments)
        changed = {f.name: [getattr(current, f.name), getattr(updated, f.name)] for f in dataclasses.fields(current)
                   if getattr(current, f.name) != getattr(updated, f.name)}
        fixed = sorted(name for name in changed if name not in LIVE_KNOBS)
        if fixed:
            raise ValueError(f"curriculum.{fixed[0]} is fixed for the life of a run; the live knobs are "
                             f"{', '.join(LIVE_KNOBS)}")
        if changed:
            self.state = self.state._replace(knobs=self.curriculum.knobs(updated))
            self.knob_changes += 1
            for name, (old, new) in changed.items():
                log.info("curriculum knob %s: %s -> %s (from the next sample on)", name, old, new)
        return changed

    def _answer_knobs(self, query: IncomingQuery) -> None:
        try:
            request = control_reply(query.payload or b"{}")
            changed = self.set_knobs(request["set"]) if "set" in request else {}
            reply = {"ok": True, "changed": changed, "knobs": self.live_knobs(), "method": self.curriculum.method}
        except ValueError as err:
            reply = {"ok": False, "error": str(err), "knobs": self.live_knobs()}
            log.warning("refused a knob change: %s", err)
        query.reply(_json(reply))

    def inspect(self, top: int = 10) -> dict[str, Any]:
        """What `impulse curriculum inspect` shows (`curriculum.stats.inspect_report`)."""
        return inspect_report(self.state, self.curriculum.spec.sizes, self.curriculum.config, self.policy_version,
                              top)

    def _answer_inspect(self, query: IncomingQuery) -> None:
        try:
            request = control_reply(query.payload or b"{}")
            top = int(request.get("top", 10))
            report = self.inspect(top)
            wanted = request.get("levels")
            arrays = tree_arrays(top_levels(self.state, self.curriculum.spec.sizes, top)) if wanted else {}
            query.reply(encode_report(self.bus.stamp, report, arrays))
        except (ValueError, TypeError, OverflowError) as err:
            query.reply(encode_refusal(self.bus.stamp, str(err)))

    def inject(self, document: Any) -> dict[str, Any]:
        """Put the level of a Kinetix level-file object into the buffer (see the module docstring): what was done
        (`slot`, `level_id`, `evicted`); ValueError with every problem, and nothing changed, when the level does not
        load at the run's size, is not a valid scene, or is buffered already."""
        level = load_level_document(document, self.curriculum.spec.sizes)
        level_id = int(level_id_values(np.asarray(level.level_id)[None])[0])
        buffer = self.state.buffer
        if level_id in set(level_id_values(np.asarray(buffer.levels.level_id)[np.asarray(buffer.filled)]).tolist()):
            raise ValueError(f"level {level_id:016x} is in the buffer already")
        evicted = bool(np.asarray(buffer.filled).all())
        self.state, slot = self._insert(self.state, level)
        self.injected += 1
        log.info("level %016x injected into buffer slot %d%s", level_id, int(slot),
                 " in place of the lowest-scored level" if evicted else "")
        return {"slot": int(slot), "level_id": f"{level_id:016x}", "evicted": evicted}

    def _answer_inject(self, query: IncomingQuery) -> None:
        try:
            request = control_reply(query.payload or b"{}")
            if "level" not in request:
                raise ValueError('an injection needs "level": a Kinetix level file\'s JSON object')
            reply = {"ok": True, **self.inject(request["level"])}
        except ValueError as err:
            reply = {"ok": False, "error": str(err)}
            log.warning("refused an injected level: %s", err)
        query.reply(_json(reply))

    def status(self) -> dict[str, Any]:
        """The status line: counts and the buffer statistics (`curriculum.stats.buffer_summary`), which is how the
        service publishes them for monitoring."""
        summary = buffer_summary(self.state, self.curriculum.spec.sizes, self.policy_version)
        return {"role": CURRICULUM_ROLE.name, "name": CURRICULUM_ID, "incarnation": self.incarnation,
                "method": self.curriculum.method, "samples": self.samples, "results": self.result_messages,
                "policy_version": self.policy_version, "knob_changes": self.knob_changes, "injected": self.injected,
                **({"refills": self.refills, "scoring": self._scoring is not None, "filling": self.filling,
                    "scored_candidates": list(self.scored_candidates),
                    "requests_held": self.requests_held,
                    "last_refill": self._last_refill, **self.scorer.counts()} if self.scorer is not None else {}),
                **({"levels_ahead": {"ready": self.maker.ready, "made": self.maker.made,
                                     "unfiltered": self.maker.unfiltered,
                                     "filter_seconds": round(self.maker.filter_seconds, 1)}}
                   if self.maker is not None else {}),
                "rejected": self.bus.rejects.counts(), "dropped_inbox_full": self._results.dropped,
                "dropped_expired_queries": self.expired_queries,
                "dropped_queries": sum(queries.dropped for queries in (self._sample_queries, self._knob_queries,
                                                                       self._inspect_queries, self._inject_queries)),
                **{k: json_scalar(v) for k, v in summary.items()}}


def _json(value: dict[str, Any]) -> bytes:
    return json.dumps(value, default=json_scalar).encode("utf-8")
