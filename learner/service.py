"""The learner service: trajectory batches in from actors, the same PPO update as fused mode, weights out.

One cycle (driven by the shared run loop):
1. answer weight queries (an actor that starts or lost track asks `weights/latest`) and note actors joining and
   leaving (liveliness);
2. the intake (`learner.intake`): take every trajectory frame waiting in the bounded inbox into the ready queue,
   its header read and checked (malformed, foreign, duplicate frames refused and counted; gaps counted as lost);
3. the intake again: take the oldest frame fit to train on off the queue, acknowledging each frame taken to its
   actor (that frees a credit, `bus.credits`); a frame of an earlier learner epoch (before a restart) or more
   than `ppo.max_policy_lag` versions old is dropped and counted instead of trained on, before its arrays are
   unpacked; the rest are unpacked and checked against the batch's schema;
4. run `ppo_update` on it, publish the new weights every `learner.publish_every` updates (a cached publication for
   late joiners, plus the queryable), and report metrics. On one host, steps 2 and 3 for the next frame run while
   the update is computed (JAX dispatches it asynchronously), before the update's metrics are read.

The learner's epoch counts its restarts. Each start claims a new one, above both the epoch stored in the
checkpoint it resumes and the last one claimed in the run directory (`claim_epoch`), so no two learner
incarnations of a run share an epoch even when one dies before its first checkpoint. Weights carry
(epoch, version), which actors adopt only in increasing order, and trajectories carry the epoch of the weights
that acted.

On several hosts (`learner.hosts`, module `learner.hosts`) one learner process runs per host, each with its own
share of the actors; they agree on every update and run it together on the batches each holds. The leader
(process 0) is the learner the rest of the run sees: weights, status under the name `learner`, checkpoints,
metrics. The others acknowledge their actors and take part in the update.

Phases. The status says what the learner does (`phase`: compiling, training, checkpointing, stopping, finished,
or evaluating its final policy, which the learner command announces before it leaves the bus) and, for a phase
that holds the loop, since when (`phase_since`), so that the launcher's display shows the wait as it goes on
(`report_phase`, which publishes at once).

Drops. Everything the learner drops or refuses is counted, and so is what the actors and the curriculum report in
their status lines (`bus.status.DropTotals`): every metrics row carries the running totals (`drops/...`,
`rejected/...`), and the checkpoint counters keep them across a restart.
"""

from __future__ import annotations

import dataclasses
import logging
import secrets
import time
from collections import Counter, deque
from pathlib import Path
from typing import Any

import jax
import numpy as np

from impulse.actors.process import actor_index
from impulse.actors.trajectory import TrajectoryBatch, episode_metrics
from impulse.actors.wire import TrajectoryWire, trajectory_template, weights_hash
from impulse.bus.codec import Rejected
from impulse.bus.evaluations import decode_evaluation
from impulse.bus.keys import ACTOR, CURRICULUM, EVALUATOR, LEARNER, RECORDER
from impulse.bus.roles import LEARNER_ROLE
from impulse.bus.service import CycleReport, Progress
from impulse.bus.session import Bus
from impulse.bus.status import DropTotals, StatusPublisher, plausible_counts, read_status
from impulse.bus.weights import encode_weights
from impulse.curriculum.stats import metric_columns
from impulse.engine.compile_once import compile_once
from impulse.engine.memory import check_fits, warn_if_gpu_sized
from impulse.engine.pytree import tree_arrays
from impulse.learner.agent import Agent
from impulse.learner.checkpoint import TRAIN, Checkpointer, CheckpointError, fine_tuning_origin, read_starting_policy
from impulse.learner.config import CheckpointConfig, LearnerConfig, PPOConfig
from impulse.learner.hosts import ONE_HOST, HostGroup, broadcast_from_leader, global_batch, local_copy
from impulse.learner.intake import DROP_COUNTS, Taken, TrajectoryIntake
from impulse.learner.non_finite import SKIPPED_COLUMN, NonFiniteGuard, NonFiniteParameters, refuse_non_finite
from impulse.learner.run_directory import existing_run
from impulse.learner.scoring import evaluation_columns
from impulse.learner.sharding import DataParallel, DeviceError, check_divisible, learner_devices
from impulse.learner.update import TrainState, make_optimizer, ppo_update

log = logging.getLogger("impulse.learner")

LEARNER_ID = LEARNER
RATE_WINDOW = 20
"""Updates over which the status line's updates/s and consumed steps/s are measured (compile time excluded)."""
EPOCH_FILE = "learner-epoch"
"""In the run directory: the last learner epoch claimed (`claim_epoch`)."""
class LearnerError(RuntimeError):
    """The learner cannot start (existing run without --resume, unusable checkpoint)."""


def claim_epoch(run_dir: Path, restored: int) -> int:
    """A learner epoch never used before in `run_dir`: one above both the epoch of the checkpoint resumed
    (`restored`) and the last one claimed there, written down (atomically) before it is used."""
    path = run_dir / EPOCH_FILE
    try:
        claimed = int(path.read_text().strip())
    except FileNotFoundError:
        claimed = 0
    except (OSError, ValueError) as err:
        log.warning("%s is unreadable (%s): epochs continue from the checkpoint's", path, err)
        claimed = 0
    epoch = max(restored, claimed) + 1
    scratch = path.with_name(f".{EPOCH_FILE}.tmp")
    scratch.write_text(f"{epoch}\n")
    scratch.replace(path)
    return epoch


class LearnerService:
    """The learner process's state and its run-loop `cycle`."""

    def __init__(self, ppo: PPOConfig, learner: LearnerConfig, checkpoint: CheckpointConfig, *, seed: int,
                 num_updates: int, batches_in_flight: int, status_every_s: float, run_dir: Path, config_toml: str,
                 bus: Bus, agent: Agent, resume: bool = False, init_from: Path | None = None,
                 wire_compact: bool = False, group: HostGroup = ONE_HOST):
        """`num_updates`: the run's length; `batches_in_flight`: the most the actors may have sent unacknowledged
        (actors x credits), which sizes the inbox; `config_toml`: the resolved run config, kept in checkpoints;
        `init_from`: fine-tuning, a run directory or shipped agent whose policy a run with no checkpoint of its own
        starts from (one that has checkpoints resumes them: a restarted learner goes on from its own);
        `wire_compact`: the actors send the compact trajectory format (`bus.wire_compact`); `group`: this
        process's place among the learner's hosts (`learner.hosts.join_hosts`), one process by default."""
        self.ppo, self.learner = ppo, learner
        self.config_toml = config_toml
        self.bus = bus
        self.group = group
        self.steps_per_batch = ppo.steps_per_update * group.count
        self.num_updates = num_updates
        optimizer = make_optimizer(ppo, self.num_updates)
        try:
            self.parallel = DataParallel(learner_devices(len(learner.devices)))
            check_divisible(ppo, self.parallel.size // group.count)
        except DeviceError as err:
            raise LearnerError(str(err)) from err
        params = agent.init(jax.random.PRNGKey(seed))
        self.train = TrainState(params, optimizer.init(params), np.asarray(0, np.int32))
        # Only the leader keeps checkpoints; it restores a resumed run and hands the state to the others.
        self.checkpoint_config = checkpoint
        self.checkpoints = Checkpointer(run_dir / checkpoint.directory, checkpoint) if group.is_leader else None
        self.update = 0
        self.env_steps = 0
        self.epoch = 0
        self.guard = NonFiniteGuard(ppo)
        self.counts: Counter[str] = Counter()
        self.peer_drops = DropTotals()
        self._rejected_before: Counter[str] = Counter()  # the learner's refusals before its restart
        self.init_from: dict[str, Any] = {}
        """Where the starting policy came from, when fine-tuning (written into every checkpoint's counters)."""
        if self.checkpoints is not None:
            self._open_checkpoints(run_dir, resume, init_from)
        self.train, self.update, self.env_steps, self.epoch = broadcast_from_leader(
            (self.train, self.update, self.env_steps, self.epoch), group)
        self.update, self.env_steps, self.epoch = int(self.update), int(self.env_steps), int(self.epoch)
        self.updates_at_start = self.update
        self.train = self.parallel.replicate(self.train)
        self._version = int(local_copy(self.train.policy_version))

        # The update sees the group's batch: every process's environments side by side.
        group_ppo = dataclasses.replace(ppo, num_envs=ppo.num_envs * group.count)
        self._template = trajectory_template(agent.spec, ppo.num_envs, ppo.num_steps)
        self._group_template = (trajectory_template(agent.spec, group_ppo.num_envs, ppo.num_steps)
                                if group.several else self._template)
        self._update = self.parallel.jit_update(
            lambda state, batch, key: ppo_update(state, batch, key, apply_fn=agent.apply,
                                                 distribution=agent.distribution, optimizer=optimizer,
                                                 config=group_ppo, minibatch_sharding=self.parallel.minibatches),
            self._group_template,
        )
        self._held: Taken | None = None  # taken, waiting for the group to agree
        self.group_stopped = False
        self._stopping = False
        self.key = jax.random.PRNGKey(seed + 7 + self.epoch)

        keys = bus.keys
        self.intake = TrajectoryIntake(bus, TrajectoryWire(self._template, agent.spec.sizes, compact=wire_compact),
                                       capacity=max(4, 2 * batches_in_flight), max_policy_lag=ppo.max_policy_lag,
                                       counts=self.counts, serves=self._serves if group.several else None)
        # Only the leader publishes weights: the learner's other processes hold the same ones.
        if group.is_leader:  # followers adopt weights only from the learner instance whose token they follow
            bus.stamp.nonce = secrets.token_hex(8)
            bus.declare_token(keys.learner_instance(bus.stamp.nonce))
        self._weights_publisher = bus.latest_publisher(keys.weights_policy) if group.is_leader else None
        self._weights_queries = bus.queryable(keys.weights_latest, 16) if group.is_leader else None
        self._alive = bus.watch_alive(keys.alive_pattern(ACTOR))
        self._peer_statuses = {role: bus.inbox(keys.status_pattern(role), 256, drop_oldest=True)
                               for role in (ACTOR, CURRICULUM, EVALUATOR, RECORDER)}
        self._evaluations = bus.inbox(keys.evaluations_all, 16, drop_oldest=True)
        self._evaluation_columns: dict[str, float] = {}  # the newest evaluation, for the next metrics row
        self._curriculum_columns: dict[str, float] = {}  # the curriculum's newest buffer statistics, for every row
        self.evaluation: dict[str, Any] = {}  # ... and for the status line
        self._status = StatusPublisher(bus, status_every_s)
        self.actors_alive: set[str] = set()
        self._weights_frame = b""
        self._weights_hash = weights_hash(self.train.params)  # shapes and dtypes only
        self._recent: deque[float] = deque(maxlen=RATE_WINDOW)  # end times of the latest updates
        self._last_metrics: dict[str, float] = {}
        self.phase = "starting"
        """What the learner does now, for its status line: compiling, training, checkpointing, evaluating ...,
        stopping, finished (`report_phase`)."""
        self.phase_since: float | None = None
        """When (wall clock) the phase began, for a phase that blocks the loop (its seconds are shown); else None."""

    def _open_checkpoints(self, run_dir: Path, resume: bool, init_from: Path | None) -> None:
        """Refuse a run directory that holds checkpoints unless resuming; restore the newest usable one, or with
        none, start from `init_from`'s policy; claim this start's learner epoch."""
        assert self.checkpoints is not None
        if self.checkpoints.latest_step() is not None:
            if not resume:
                self.checkpoints.close()
                raise LearnerError(existing_run(run_dir))
            self._restore()
        elif resume and self.checkpoints.set_aside():
            self.checkpoints.close()
            raise LearnerError(f"cannot resume: {self.checkpoints.nothing_usable()}")
        elif init_from is not None:
            self._start_from_policy(init_from)
        elif resume:
            log.info("nothing to resume in %s yet: starting fresh", self.checkpoints.directory)
        self.epoch = claim_epoch(run_dir, self.epoch)

    def _restore(self) -> None:
        assert self.checkpoints is not None
        try:
            restored = self.checkpoints.restore({TRAIN: self.train})
        except CheckpointError as err:
            raise LearnerError(str(err)) from err
        counters = restored.counters
        try:
            refuse_non_finite(restored.items[TRAIN].params, f"to resume from checkpoint {restored.step}")
        except NonFiniteParameters as err:
            raise LearnerError(f"{err}: it was written before Impulse refused such parameters; resume from an "
                               "older checkpoint (move the newer ones out of the checkpoints folder)") from None
        self.train = restored.items[TRAIN]
        self.update = int(counters["update"])
        self.guard.skipped = int(counters.get(SKIPPED_COLUMN, 0))
        self.env_steps = int(counters["env_steps"])
        self.epoch = int(counters.get("learner_epoch", 0))
        self.counts.update(plausible_counts(counters.get("drop_counts")))
        self._rejected_before.update(plausible_counts(counters.get("rejected")))
        self.peer_drops.restore(counters.get("peer_drops"))
        self.init_from = fine_tuning_origin(counters)
        log.info("resumed from checkpoint %d (update %d, policy version %d, %s env steps, epoch %d)",
                 restored.step, self.update, int(self.train.policy_version),
                 f"{self.env_steps:,}", self.epoch + 1)

    def _start_from_policy(self, source: Path) -> None:
        """Fine-tuning: the parameters of `source`'s newest intact checkpoint, with this run's fresh optimiser,
        from update 0."""
        assert self.checkpoints is not None
        try:
            start = read_starting_policy(source, self.train, self.checkpoint_config)
            refuse_non_finite(start.params, "to start from its policy")
        except (CheckpointError, NonFiniteParameters) as err:
            self.checkpoints.close()
            raise LearnerError(f"--init-from {source}: {err}") from err
        self.train = self.train._replace(params=start.params)
        self.init_from = start.origin

    @property
    def version(self) -> int:
        """The policy version of the newest update dispatched (kept on the host, so that reading it never waits for
        the device)."""
        return self._version

    # -- weights ------------------------------------------------------------------------------------------

    def _publish_weights(self) -> None:
        self.bus.stamp.acting_for(self.epoch, self.version)
        if self._weights_publisher is None:
            return
        arrays = tree_arrays(local_copy(self.train.params))
        refuse_non_finite(arrays, f"to publish policy version {self.version}")
        self._weights_frame = encode_weights(self.bus.stamp, arrays, self._weights_hash)
        self._weights_publisher.put(self._weights_frame)
        self.counts["weights_published"] += 1

    def _answer_queries(self) -> None:
        if self._weights_queries is None:
            return
        for query in self._weights_queries.poll():
            query.reply(self._weights_frame)

    # -- actors -------------------------------------------------------------------------------------------

    def _watch_actors(self) -> None:
        for key, alive in self._alive.poll():
            _, name = self.bus.keys.parse_alive(key)
            if alive and name not in self.actors_alive:
                log.info("actor %s joined", name)
                self.actors_alive.add(name)
            elif not alive and name in self.actors_alive:
                log.warning("actor %s left", name)
                self.actors_alive.discard(name)

    # -- trajectories -------------------------------------------------------------------------------------

    def _serves(self, actor: str) -> bool:
        """Whether this learner process trains on `actor`'s batches (its share of the actors, `HostGroup`)."""
        index = actor_index(actor)
        return index is not None and self.group.serves_actor(index)

    def _hear_peers(self) -> None:
        """The status lines of the actors, the curriculum, the evaluator and the recorder, for their drop counters,
        and the curriculum's buffer statistics for the metrics rows (the same `curriculum_...` columns as the fused
        trainer's)."""
        for inbox in self._peer_statuses.values():
            for received in inbox.poll():
                try:
                    heard = read_status(received, self.bus.keys)
                except Rejected as err:
                    self.bus.rejects.record(err.reason, received.key, err.detail)
                    continue
                self.peer_drops.note(heard)
                if heard.role == CURRICULUM:
                    self._curriculum_columns = metric_columns(heard.status)

    def _hear_evaluations(self) -> None:
        """The evaluator's scores of a policy: written to the next metrics row (`eval/...` columns, as in
        `impulse train`) and shown on the status line."""
        for received in self._evaluations.poll():
            try:
                heard = decode_evaluation(received.payload, self.bus.keys.run)
            except Rejected as err:
                self.bus.rejects.record(err.reason, received.key, err.detail)
                continue
            self._evaluation_columns = {**evaluation_columns(heard.levels, heard.groups, heard.policy_version),
                                        "eval/skipped": float(heard.skipped)}
            self.evaluation = {"policy_version": heard.policy_version, "groups": heard.groups,
                               "mean": self._evaluation_columns["eval/mean"]}

    def rejected(self) -> dict[str, int]:
        """Messages the learner refused, by reason, over the whole run (restarts included)."""
        return dict(self._rejected_before + Counter(self.bus.rejects.counts()))

    def drop_metrics(self) -> dict[str, int]:
        """Every drop and refusal of the run so far, as metrics.jsonl columns: `drops/<counter>` and
        `rejected/<reason>` for the learner's own, `drops/<role>/<counter>` and `rejected/<role>/<reason>` for
        the other processes' (summed over their incarnations)."""
        metrics = {f"drops/{name}": int(self.counts.get(name, 0)) for name in DROP_COUNTS}
        metrics.update({f"rejected/{reason}": count for reason, count in sorted(self.rejected().items())})
        for name, count in self.peer_drops.totals().items():
            role, _, counter = name.partition("/")
            prefix = "rejected" if counter.startswith("rejected/") else "drops"
            metrics[f"{prefix}/{role}/{counter.removeprefix('rejected/')}"] = count
        return metrics

    def _take(self) -> Taken | None:
        """The oldest batch fit to train on (`TrajectoryIntake.take`, for this learner's epoch and version)."""
        return self.intake.take(self.epoch, self._version, republish=self._publish_weights)

    # -- the cycle ----------------------------------------------------------------------------------------

    def _rate(self) -> float:
        """Updates per second over the latest RATE_WINDOW updates (0 until two are done)."""
        if len(self._recent) < 2 or self._recent[-1] <= self._recent[0]:
            return 0.0
        return (len(self._recent) - 1) / (self._recent[-1] - self._recent[0])

    def status(self) -> dict[str, Any]:
        rate = self._rate()
        return {
            "role": LEARNER_ROLE.name,
            "name": self.group.name(LEARNER_ID),
            "host": f"{self.group.index}/{self.group.count}",
            "epoch": self.epoch,
            "policy_version": self.version,
            "update": self.update,
            "num_updates": self.num_updates,
            "env_steps": self.env_steps,
            "updates_per_s": rate,
            "consumed_steps_per_s": rate * self.steps_per_batch,
            "queue": self.intake.queued,
            "ingested": self.intake.ingested.status(),
            "actors": sorted(self.actors_alive),
            "actor_lag": self.intake.actor_lag,
            "lag_histogram": {str(k): v for k, v in sorted(self.intake.lags.items())},
            "rejected": self.rejected(),
            "dropped_queries": self._weights_queries.dropped if self._weights_queries is not None else 0,
            "solve_rate": self._last_metrics.get("window_solve_rate"),
            "finished": self.finished(),
            "phase": self.phase,
            **({"phase_since": self.phase_since} if self.phase_since is not None else {}),
            "peer_drops": self.peer_drops.totals(),
            "evaluation": self.evaluation,
            "skipped_non_finite": self.guard.skipped,
            "stale_streak": self.intake.stale_streak,
            "nonce": self.bus.stamp.nonce,
            **{name: 0 for name in DROP_COUNTS},
            **dict(self.counts),
        }

    def cycle(self) -> CycleReport | None:
        self.guard.check()  # NonFiniteUpdates: too many skipped updates in a row
        if self._status.due():
            self._status.publish(self.status())
        self._answer_queries()
        self._watch_actors()
        self._hear_peers()
        self._hear_evaluations()
        self.intake.ingest()
        self.intake.acks.refresh()
        if self._held is None:
            self._held = self._take()
        if not self._group_ready():
            return None
        assert self._held is not None
        batch = self._held.batch
        self._held = None
        self.key, update_key = jax.random.split(self.key)
        placed = self._place(batch)
        self.train, losses = self._update(self.train, placed, update_key)
        self._version += 1
        self.update += 1
        if not self.group.several and not self.finished():
            # The next frame is read while the device computes this update.
            self.intake.ingest()
            self._held = self._take()
        self.env_steps += self.steps_per_batch
        if self.update % self.learner.publish_every == 0:
            self._publish_weights()
        # The batch's own episode counts on one host (host arrays, as it arrived); the group's on several.
        episodes = local_copy(placed.episodes) if self.group.several else batch.episodes
        metrics = {k: float(v) for k, v in local_copy({**losses, **episode_metrics(episodes)}).items()}
        self.guard.note(self.update, metrics)
        metrics.update(
            **self.guard.columns(),
            actor=float(batch.actor_id),
            steps_per_s=self._rate() * self.steps_per_batch,
            queue=self.intake.queued,
            **self.drop_metrics(),
            **self._curriculum_columns,
            **self._evaluation_columns,
        )
        self._evaluation_columns = {}  # each evaluation in one row
        if self.learner.slow_down_s:
            time.sleep(self.learner.slow_down_s)
        self._recent.append(time.monotonic())
        return CycleReport(env_steps=self.steps_per_batch, updates=1, metrics=metrics)

    def _group_ready(self) -> bool:
        """Whether to update now: this process holds a batch and, on several hosts, so does every other (they
        agree once per cycle). A process that is stopping says so instead; then the whole group stops."""
        if not self.group.several:
            return self._held is not None
        agreed = self.group.agree(have_batch=self._held is not None, stopping=self._stopping)
        if agreed["stopping"].any():
            self.group_stopped = True
            return False
        return bool(agreed["have_batch"].all())

    def _place(self, batch: TrajectoryBatch) -> TrajectoryBatch:
        """The batch the update runs on: this one on the learner's devices, or on several hosts the group's,
        of which this one is this process's part."""
        if not self.group.several:
            return self.parallel.place_batch(batch)
        return global_batch(jax.device_get(batch), self.parallel.batch_shardings(self._group_template), self.group)

    def request_stop(self) -> None:
        """A signal arrived (the run loop's stop flag): on several hosts, the next agreement tells the group."""
        self._stopping = True

    def note_window(self, window: dict[str, float]) -> None:
        """The run loop's window summary, for the status line."""
        self._last_metrics["window_solve_rate"] = window.get("solve_rate")

    def report_phase(self, phase: str, blocking: bool = True) -> None:
        """Say what the learner does now ("compiling", "checkpointing", "evaluating 42 levels x 20 attempts") in a
        status published at once, so that the launcher's display shows it while the loop waits on it (`blocking`:
        with its seconds so far)."""
        self.phase = phase
        self.phase_since = time.time() if blocking else None
        self._status.publish(self.status())

    def _back_to_training(self) -> None:
        """The blocking phase is over: the next status says "training" (published when due)."""
        self.phase, self.phase_since = "training", None

    def save(self, summary: dict[str, float]) -> None:
        self.note_window(summary)
        if self.checkpoints is None:
            return
        self.report_phase("checkpointing")
        train = local_copy(self.train) if self.group.several else self.train
        refuse_non_finite(train.params, f"checkpoint {self.update}")
        counters = {"update": self.update, "env_steps": self.env_steps, "learner_epoch": self.epoch,
                    SKIPPED_COLUMN: self.guard.skipped,
                    "policy_version": self.version, "drop_counts": dict(self.counts),
                    "rejected": self.rejected(), "peer_drops": self.peer_drops.state(), **self.init_from, **summary}
        self.checkpoints.save(self.update, {TRAIN: train}, counters, self.config_toml,
                              solve_rate=summary.get("solve_rate"))
        self._back_to_training()

    def start(self) -> None:
        """Publish the starting weights (fresh, or the resumed checkpoint's), which actors wait for; then compile
        the update and check that it fits in memory (`DoesNotFit`, naming the sizes and an override that would
        fit). The compiled program is the one the first update runs: `jit` reuses it."""
        self._publish_weights()
        ppo = self.ppo
        warn_if_gpu_sized(ppo.num_envs, ppo.num_steps)
        log.info("compiling the update (%s envs x %s steps) ...", ppo.num_envs, ppo.num_steps)
        self.report_phase("compiling")
        started = time.perf_counter()
        compiled = compile_once(self._update.lower(self.train, self._group_template, self.key), "the learner's update")
        log.info("compiled the update in %.1f s", time.perf_counter() - started)
        check_fits(compiled, "the learner's update", ppo.num_envs, ppo.num_steps)
        self._back_to_training()

    def progress(self) -> Progress:
        return Progress(env_steps_done=self.env_steps, updates_done=self.update,
                        total_env_steps=self.num_updates * self.steps_per_batch)

    def finished(self) -> bool:
        return self.update >= self.num_updates

    def close(self) -> None:
        """Wait for checkpoints, and tell whoever watches (actors on other hosts, which no launcher stops) whether
        the run is finished. On several hosts, a process that stops before the run is finished (a signal, an
        error) first tells the others, which are waiting for it in their next agreement."""
        if self.group.several and not self.group_stopped and not self.finished():
            self._stopping = True
            self._group_ready()
        if self.checkpoints is not None:
            self.checkpoints.close()
        self.phase, self.phase_since = ("finished" if self.finished() else "stopping"), None
        self._status.publish(self.status())
