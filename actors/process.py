"""The actor process: environments on this process's JAX device, driven by the newest policy weights, publishing
trajectory batches to the learner and per-level results to whoever scores levels.

One cycle (driven by the shared run loop):
1. adopt the newest weights that arrived (only between rollouts, so one batch has one behaviour version);
2. check credits: at most `actors.credits` batches may be in flight to the learner. Out of credit, the actor
   either waits ("wait") or keeps rolling out and holds back only its newest batch ("drop_oldest"; each replaced
   batch is counted as dropped), so memory stays flat however slow the learner is;
3. run the jitted rollout of `ppo.num_steps` steps in `ppo.num_envs` environments on the next level batch;
4. publish the batch (its behaviour version and the learner epoch of the weights that acted ride in the frame
   header) and the per-level results, and report steps/s and counts on the status line;
5. while a recorder listens (`learner.recorder`), publish the level batch it plays on `actor/played/<actor>`
   (when it changes, when a recorder appears, and every `bus.levels.PLAYED_LEVELS_EVERY_S` for a fixed level
   set), so that recorded episodes come with their levels;
6. with a monitor, offer the watched environments' frames to it (`monitor.stream`): the rollout recorded them on
   the device, the monitor's thread copies and logs them, and a full queue or the rate limit drops them rather
   than slowing the actor.

Starting. Before its first cycle the actor compiles its rollout ahead of time for the shapes of its level source's
batches (while a curriculum service may still be starting), checks the compiled program against the memory free
(`engine.memory.check_fits`), then fetches its first level batch and resets its environments on it. A program
that does not fit is refused with the sizes and an override (`impulse actor` then exits with the status that
makes `impulse launch` give up at once), instead of being killed by the kernel in its first rollout.

Weights. The actor follows the learner (`actors.follow.LearnerFollower`): it adopts only intact, strictly newer
weights of its network (a restarted learner's new epoch excepted), ignores repeats and refuses replays. In
lockstep (`actors.lockstep`) it rolls out only with weights newer than those of its last batch, so actor and
learner take turns and a launch is reproducible (docs/distributed.md).

Credits (both halves of the protocol: `bus.credits`; the actor's is its `CreditLedger`). The learner
acknowledges every batch it takes off its queue (trained on or dropped as stale) on `credit/<actor>` with the
highest sequence number taken; an actor's batches in flight are the ones sent after that. Acknowledgements name
the actor's incarnation (a random number drawn at start), so a restarted actor is not confused by
acknowledgements meant for its predecessor; and they carry the learner's epoch, so when a restarted learner (new
epoch) appears, whatever was in flight to the old one is written off at once, as it is when the learner's
liveliness token goes and comes back (the link to it broke: a router restart, a network partition). If no
acknowledgement arrives while out of credit for `actors.credit_timeout_s`, or for longer while the learner's own
pace says the batch may still be queued (`CreditLedger.deadline_s`: a slow learner, a loaded machine), the
batches in flight are written off too.

Stopping. The actor stops by itself when the learner has finished the run: its latest status (on the learner's own
status key) says so and its liveliness token is gone (`LearnerFollower.learner_finished`).
"""

from __future__ import annotations

import logging
import secrets
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import jax
import numpy as np

from impulse.actors.config import ActorConfig
from impulse.actors.follow import LearnerFollower
from impulse.actors.levels import LevelSource
from impulse.actors.rollout import RolloutCarry, rollout, start_rollout
from impulse.actors.trajectory import TrajectoryBatch, episode_metrics, make_batch
from impulse.actors.wire import TrajectoryWire
from impulse.bus.codec import Rejected
from impulse.bus.credits import CreditLedger, decode_credit
from impulse.bus.levels import PLAYED_LEVELS_EVERY_S, encode_level_batch, encode_level_results
from impulse.bus.roles import ACTOR_ROLE
from impulse.bus.service import CycleReport, Progress
from impulse.bus.session import Bus
from impulse.bus.status import StatusPublisher
from impulse.bus.trajectories import encode_trajectory
from impulse.curriculum.results import LevelResults
from impulse.curriculum.state import LevelBatch
from impulse.curriculum.wire import level_batch_arrays, results_arrays
from impulse.engine.compile_once import compile_once
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.memory import check_fits
from impulse.engine.pytree import tree_arrays
from impulse.monitor.config import MonitorConfig

if TYPE_CHECKING:
    from impulse.monitor.rollouts import RolloutStream
    from impulse.monitor.stream import Monitor

log = logging.getLogger("impulse.actor")


class ActingAgent(Protocol):
    """What an actor needs of the agent (`learner.agent.Agent` fits): the environment it was built for, its policy
    (the rollout's `Policy`) and fresh parameters, whose shapes incoming weights are checked against."""

    @property
    def spec(self) -> EnvSpec: ...

    def act(self, params: Any, obs: Any, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]: ...

    def init(self, key: jax.Array) -> Any: ...


LevelResultsFn = Callable[[Any, TrajectoryBatch, int], LevelResults]
"""(params, batch, rows) -> the batch's per-level results in `rows` rows, for the curriculum (traced under jit)."""


def actor_name(index: int) -> str:
    return f"actor-{index}"


def actor_index(name: str) -> int | None:
    """The number in an actor's name (`actor_name`), None for a name not made by it."""
    prefix, _, number = name.rpartition("-")
    return int(number) if prefix == "actor" and number.isdigit() else None


class Actor:
    """One actor process's state and its run-loop `cycle`."""

    def __init__(self, actors: ActorConfig, *, num_envs: int, num_steps: int, seed: int, index: int, bus: Bus,
                 agent: ActingAgent, env_params: EnvParams, levels: LevelSource, level_results: LevelResultsFn,
                 env_steps_goal: int = 0, monitor: Monitor | None = None,
                 monitor_config: MonitorConfig | None = None, restart_envs: bool = False):
        """`num_envs` x `num_steps` per batch, every environment restarted on each new level batch when
        `restart_envs` (the run's `ppo` section); `seed`: the run's; `level_results`: how
        per-level results are computed from a batch (`learner.curriculum_inputs.batch_level_results` with the
        agent and the PPO settings); `env_steps_goal`: this actor's share of the run, for its progress line;
        `monitor_config` says what to stream when there is a `monitor`."""
        self.actors = actors
        self.monitor = monitor
        self.index = index
        self.name = actor_name(index)
        self.bus = bus
        self.agent = agent
        self.levels = levels
        self.incarnation = secrets.randbits(31)
        self._stop_requested = False
        self.num_envs, self.num_steps = num_envs, num_steps
        self.env_steps_goal = env_steps_goal
        # Seeded by the run, the actor and the incarnation: a restarted actor does not replay its predecessor.
        # In lockstep the incarnation is left out, so that the same seed gives the same run.
        salt = 0 if actors.lockstep else self.incarnation
        seed = (seed * 1_000_003 + index * 7919 + salt) % 2**32
        self.key = jax.random.PRNGKey(seed)
        self.env_params = env_params
        self.level_results = level_results
        self.carry: RolloutCarry | None = None  # set by `start`, from the first level batch
        spec, steps = agent.spec, self.num_steps
        monitor_config = monitor_config or MonitorConfig()
        self.watch = min(monitor_config.watch_envs, self.num_envs) if monitor is not None else 0
        watch = self.watch

        def actor_rollout(params: Any, carry: RolloutCarry, batch: Any) -> Any:
            return rollout(agent.act, params, spec, env_params, carry, batch.levels, steps, batch.train, watch,
                           restart_envs)

        # Compiled ahead of time by `start`, which checks that it fits in memory; `jit` then reuses that program.
        self._rollout = jax.jit(actor_rollout, donate_argnums=1)
        self._params_template = jax.eval_shape(agent.init, jax.random.PRNGKey(0))
        self.follow = LearnerFollower(bus, self._params_template)

        keys = bus.keys
        self._traj = bus.publisher(keys.traj(self.name))
        self._results = bus.publisher(keys.levels_results(self.name))
        self._played = bus.publisher(keys.levels_played(self.name))
        self._played_ids: np.ndarray | None = None
        self._played_at = -float("inf")
        self._credits = bus.inbox(keys.credit(self.name), 64, drop_oldest=True)
        self._status = StatusPublisher(bus, bus.config.status_every_s)

        self._wire: TrajectoryWire | None = None
        self.ledger = CreditLedger(self.incarnation, actors.credits, actors.credit_timeout_s,
                                   queued_ahead=actors.num_actors * actors.credits)
        self._held: TrajectoryBatch | None = None  # drop_oldest: the newest batch waiting for a credit
        self._acted: tuple[int, int] | None = None  # (epoch, version) of the weights of the latest rollout
        self.counts = {"sent": 0, "dropped_no_credit": 0}
        self._steps_done = 0
        self._stream: RolloutStream | None = None
        if monitor is not None and self.watch:
            from impulse.monitor.rollouts import (
                RolloutStream,  # rerun only with a monitor (deploy/runtime/monitoring.py)
            )

            self._stream = RolloutStream(monitor, self.name, self.watch, self.num_steps, monitor_config.contacts)
        self._started = time.monotonic()
        self._last_cycle_s = 0.0

    # -- weights ------------------------------------------------------------------------------------------

    @property
    def params(self) -> Any:
        return self.follow.params

    @property
    def version(self) -> int:
        return self.follow.version

    @property
    def epoch(self) -> int:
        return self.follow.epoch

    def _follow_learner(self) -> None:
        """Adopt the newest weights; what was in flight to a learner that restarted, or whose link broke (its token
        went and came back: a router restart, a network partition), is written off now rather than after the
        credit timeout. A batch that did arrive is still trained on; its late acknowledgement is ignored."""
        events = self.follow.poll()
        if events.new_epoch and self.in_flight:
            log.info("the learner restarted: %d batches in flight written off", self.in_flight)
            self.ledger.write_off()
        if events.learner_back and self.in_flight:
            log.info("the learner is back after an interruption: %d batches in flight written off", self.in_flight)
            self.ledger.write_off()

    # -- credits ------------------------------------------------------------------------------------------

    def _receive_acks(self) -> None:
        for received in self._credits.poll():
            try:
                credit = decode_credit(received.payload, self.bus.keys.run)
            except Rejected as err:
                self.bus.rejects.record(err.reason, "credit", err.detail)
                continue
            self.ledger.heard(credit, self.epoch)

    @property
    def seq(self) -> int:
        """Batches sent by this incarnation."""
        return self.ledger.seq

    @property
    def in_flight(self) -> int:
        return self.ledger.in_flight

    def credit_deadline_s(self) -> float:
        """How long to wait out of credit before writing the batches in flight off, at the learner's recent pace
        (`bus.credits.CreditLedger.deadline_s`)."""
        return self.ledger.deadline_s(self.follow.seconds_per_version)

    def _has_credit(self) -> bool:
        """Whether a batch may be sent now (`bus.credits.CreditLedger.may_send`)."""
        return self.ledger.may_send(self.follow.seconds_per_version)

    # -- sending ------------------------------------------------------------------------------------------

    def _send(self, batch: TrajectoryBatch) -> None:
        seq = self.ledger.next_seq()
        batch = batch._replace(seq=np.int32(seq))
        if self._wire is None:  # the layout of the batches this actor sends, from the first one
            self._wire = TrajectoryWire(batch, self.agent.spec.sizes, compact=self.bus.config.wire_compact,
                                        float16=self.bus.config.wire_float16)
        self._traj.put(encode_trajectory(self.bus.stamp, self._wire.pack(tree_arrays(batch)), seq=seq,
                                         incarnation=self.incarnation, actor_index=self.index,
                                         layout=self._wire.format))
        self.counts["sent"] += 1

    def _offer_played_levels(self, batch: LevelBatch) -> None:
        """Publish the level batch about to be played, if a recorder listens and it has not heard it lately. While
        none listens the batch counts as unheard, so a recorder that (re)starts hears it at this actor's next
        cycle rather than a repeat later."""
        if not self._played.matching_status.matching:
            self._played_ids = None
            return
        ids = np.asarray(jax.device_get(batch.levels.level_id))
        now = time.monotonic()
        if (self._played_ids is not None and np.array_equal(ids, self._played_ids)
                and now - self._played_at < PLAYED_LEVELS_EVERY_S):
            return
        self._played.put(encode_level_batch(self.bus.stamp, level_batch_arrays(jax.device_get(batch))))
        self._played_ids, self._played_at = ids, now

    def _publish_results(self, results: LevelResults) -> None:
        arrays = results_arrays(results)
        if arrays["episodes"].size:
            self._results.put(encode_level_results(self.bus.stamp, arrays, self.seq))

    # -- the cycle ----------------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        elapsed = time.monotonic() - self._started
        return {
            "role": ACTOR_ROLE.name,
            "name": self.name,
            "incarnation": self.incarnation,
            "steps_per_s": self._steps_done / elapsed if elapsed > 0 else 0.0,
            "last_cycle_s": self._last_cycle_s,
            "policy_version": self.version,
            "learner_epoch": self.epoch,
            "in_flight": self.in_flight,
            "levels": self.levels.description,
            "waiting": self._waiting_for(),
            "rejected": self.bus.rejects.counts(),
            "weights_latency_ms": self.follow.latency_ms(),
            **self.counts,
            "written_off": self.ledger.written_off,
            **self.follow.counts,
            **({"monitor": self.monitor.status()} if self.monitor is not None else {}),
        }

    def _waiting_for(self) -> str:
        """What the actor waits for, if anything: levels first, since before its first level batch (the curriculum
        service still filling its buffer) it has not started following the learner's weights."""
        if self.levels.waiting:
            return "levels"
        if self.params is None or self._awaits_next_weights():
            return "weights"
        return "credit" if self.in_flight >= self.actors.credits else ""

    def _publish_status_if_due(self) -> None:
        if self._status.due():
            self._status.publish(self.status())

    def request_stop(self) -> None:
        """The run loop's stop signal: a cycle waiting for levels gives up instead of waiting on, since the
        curriculum service it waits for may be stopping too."""
        self._stop_requested = True

    def _keep_waiting_for_levels(self) -> bool:
        self._publish_status_if_due()
        return not self._stop_requested

    def start(self) -> None:
        """Compile the rollout for the level source's batch shapes and check that it fits in memory (`DoesNotFit`,
        naming the sizes and an override that would fit), then fetch the first level batch (from the curriculum
        service, waiting for it as long as no stop is asked) and reset the environments on it, before the actor
        waits for weights and takes levels."""
        self.key, level_key, rollout_key = jax.random.split(self.key, 3)
        template = self.levels.template

        def start_on(batch: Any, key: jax.Array) -> Any:
            return start_rollout(self.agent.spec, self.env_params, batch.levels, self.num_envs, key, batch.train)

        # Compiled from the batches' shapes before the first batch comes, so that the compile overlaps the wait
        # for a curriculum service that is itself still compiling.
        self._compile_rollout(jax.eval_shape(start_on, template, rollout_key), template)
        first = self.levels.next_batch(level_key, self._keep_waiting_for_levels)
        if first is None:  # only a stop request ends a wait without levels
            return
        self.carry = start_on(first, rollout_key)
        rows = self.num_envs + int(first.train.shape[0])  # a window touches at most E + K levels
        level_results = self.level_results
        self._level_results = jax.jit(lambda params, batch: level_results(params, batch, rows))

    def _compile_rollout(self, carry: Any, batch: Any) -> None:
        """Compile the rollout for the shapes of the weights, a carry like `carry` and a level batch like `batch`
        (the program the first cycle runs: `jit` reuses it), and refuse it when it needs more memory than this
        device has free."""
        log.info("compiling the rollout (%s envs x %s steps) ...", self.num_envs, self.num_steps)
        started = time.perf_counter()
        compiled = compile_once(self._rollout.lower(self._params_template, carry, batch), f"{self.name}'s rollout")
        log.info("compiled the rollout in %.1f s", time.perf_counter() - started)
        check_fits(compiled, f"{self.name}'s rollout", self.num_envs, self.num_steps)

    def cycle(self) -> CycleReport | None:
        self._publish_status_if_due()
        self._follow_learner()
        self._receive_acks()
        if self.params is None or self.carry is None:
            return None
        if self._held is not None and self._has_credit():
            self._send(self._held)
            self._held = None
        drop_oldest = self.actors.when_no_credit == "drop_oldest"
        if not self._has_credit() and not drop_oldest:
            return None
        if self._awaits_next_weights():
            return None
        start, started_at = time.monotonic(), time.time()
        self.key, level_key = jax.random.split(self.key)
        levels = self.levels.next_batch(level_key, self._keep_waiting_for_levels)
        if levels is None:
            return None
        self._offer_played_levels(levels)
        self._acted = (self.epoch, self.version)
        self.carry, steps, train_mask, stats, watched = self._rollout(self.params, self.carry, levels)
        batch = make_batch(steps, self.carry.obs, self.version, actor_id=self.index, train_mask=train_mask,
                           episodes=stats)
        results = self._level_results(self.params, batch) if self.levels.reports_results else None
        batch = jax.device_get(batch)
        if self._has_credit():
            self._send(batch)
        else:
            if self._held is not None:
                self.counts["dropped_no_credit"] += 1
            self._held = batch
        if results is not None:
            self._publish_results(results)
        self._last_cycle_s = time.monotonic() - start
        if self._stream is not None and watched is not None:
            self._stream.after_rollout(batch.steps, watched.state, watched.actuation, self.version, started_at,
                                       self._last_cycle_s)
        env_steps = self.num_envs * self.num_steps
        self._steps_done += env_steps
        metrics = {name: float(value) for name, value in jax.device_get(episode_metrics(stats)).items()}
        metrics.update(policy_version=float(self.version), steps_per_s=env_steps / self._last_cycle_s)
        return CycleReport(env_steps=env_steps, updates=0, metrics=metrics)

    def _awaits_next_weights(self) -> bool:
        """In lockstep, whether the weights at hand already acted (the learner has not yet published the update
        made on the latest batch)."""
        return self.actors.lockstep and self._acted is not None and (self.epoch, self.version) <= self._acted

    def progress(self) -> Progress:
        """An actor starts from nothing; its goal is its share of the run's env steps (for its progress line)."""
        return Progress(total_env_steps=self.env_steps_goal)

    def save(self, summary: dict[str, float]) -> None:
        """An actor keeps no state worth a checkpoint: the learner and the curriculum own the run."""

    def close(self) -> None:
        """Nothing to release: the bus session and the monitor belong to the process that made them."""

    def finished(self) -> bool:
        """When the learner's latest status says the run is finished and the learner has left (see the module
        docstring): on one machine the launcher stops the actors anyway, but actors on other hosts would otherwise
        wait for weights that never come."""
        if self.follow.learner_finished:
            log.info("the learner finished the run: %s stops", self.name)
            return True
        return False
