"""A fused training run from its configuration sections (`learner.config.TrainingSetup`), as a service the shared
run loop drives (`deploy.runtime.runloop`): levels, trainer, resume, checkpoints, final evaluation. `impulse train`
composes it with the loop.

Run directory layout: `config.toml` (the resolved config, written by the command), `metrics.jsonl` (one line per
update), `checkpoints/<update>/` (orbax items `train`, `envs` and, on random levels, `curriculum`), `eval.json`
(the final evaluation).
A run killed at any point resumes from its newest complete checkpoint with `--resume`; the iterations after it
are recomputed exactly, so the resumed run ends with the same parameters as one that was never interrupted.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from impulse.bus.service import CycleReport, Progress
from impulse.curriculum.methods import make_curriculum
from impulse.curriculum.stats import buffer_summary, metric_columns
from impulse.engine.compile_once import compile_once
from impulse.engine.env.spec import EnvParams
from impulse.engine.levels.level import Level
from impulse.engine.levels.sets import HANDMADE, RANDOM, LevelSetError, load_level_set
from impulse.engine.memory import DoesNotFit, check_fits, warn_if_gpu_sized
from impulse.engine.physics.sizes import SceneSizes
from impulse.learner.agent import Agent, env_and_agent
from impulse.learner.checkpoint import (
    CURRICULUM,
    ENVS,
    TRAIN,
    Checkpointer,
    CheckpointError,
    Restored,
    fine_tuning_origin,
    read_starting_policy,
)
from impulse.learner.config import TrainingSetup
from impulse.learner.evaluate import RecordedEpisodes, record_episodes
from impulse.learner.fused import FusedCarry, FusedTrainer
from impulse.learner.networks import describe_parameters
from impulse.learner.non_finite import SKIPPED_COLUMN, NonFiniteGuard, NonFiniteParameters, refuse_non_finite
from impulse.learner.run_directory import existing_run
from impulse.learner.scoring import (
    LevelScored,
    LevelSets,
    evaluating_phase,
    evaluation_columns,
    format_scores,
    load_level_sets,
    score_policy,
)

log = logging.getLogger(__name__)

PhaseReport = Callable[[str], None]
"""Told what a run does now, when it starts a phase that takes a while ("compiling the training step (64 envs x
64 steps)"): a command's progress display. The same phases are logged."""


FINAL_EVALUATION = "evaluating the final policy"
"""The phase a distributed run's learner announces before it leaves the bus to evaluate its final policy."""


def _report(on_phase: PhaseReport | None, phase: str) -> None:
    if on_phase is not None:
        on_phase(phase)


class RunError(RuntimeError):
    """A run cannot start or resume (existing run directory, mismatched checkpoint, no levels)."""


def _levels(config: TrainingSetup, sizes) -> tuple[list[str], Level | None]:
    if config.env.levels == RANDOM:
        return [], None
    try:
        return load_level_set(config.env.levels, sizes)
    except ValueError as err:  # the message names the set and every file that failed, with its problems
        raise RunError(f"env.levels: {err}") from err


def _eval_sets(config: TrainingSetup, sizes: SceneSizes, train_names: list[str],
               train_levels: Level | None) -> LevelSets | None:
    """The evaluation levels: `eval.levels` (one or more sets), else the training levels, else (on random
    levels) the hand-made set; None, with a warning, when they cannot be loaded."""
    spec = config.eval.levels or (HANDMADE if train_levels is None else "")
    if not spec:
        return LevelSets(train_names, train_levels, {config.env.levels: train_names})
    try:
        return load_level_sets(spec, sizes)
    except LevelSetError as err:
        log.warning("no evaluation: %s%s", "eval.levels: " if config.eval.levels else "", err)
        return None


def build(config: TrainingSetup) -> tuple[FusedTrainer, Agent, list[str], Level | None]:
    spec, env_params, agent = env_and_agent(config.env, config.network)
    names, levels = _levels(config, spec.sizes)
    num_updates = config.ppo.updates_for(config.total_env_steps)
    # A fixed level set has no curriculum (the run configuration refuses a method other than "dr" with one).
    curriculum = None if levels is not None else make_curriculum(config.curriculum, spec, env_params,
                                                                 config.ppo.num_envs)
    trainer = FusedTrainer(agent, env_params, config.ppo, num_updates, curriculum=curriculum)
    return trainer, agent, names, levels


class FusedRun:
    """The fused trainer as a run-loop service: one `cycle` is one jitted iteration (rollout + PPO update)."""

    def __init__(self, config: TrainingSetup, run_dir: Path, config_toml: str, resume: bool = False,
                 stop_after_updates: int | None = None, init_from: Path | None = None,
                 on_phase: PhaseReport | None = None):
        """`on_phase`: told of the phases that take a while (restoring, compiling, evaluating); `self.on_phase`
        may be changed later (a command's heartbeat while the run is built, then its progress line)."""
        self.config = config
        self.on_phase = on_phase
        self.run_dir = run_dir
        self.config_toml = config_toml
        self.trainer, self.agent, self.names, self.levels = build(config)
        self.steps_per_update = config.ppo.steps_per_update
        self.checkpoints = Checkpointer(run_dir / config.checkpoint.directory, config.checkpoint)
        if not resume and self.checkpoints.latest_step() is not None:
            self.checkpoints.close()
            raise RunError(existing_run(run_dir))
        warn_if_gpu_sized(config.ppo.num_envs, config.ppo.num_steps)
        init, iterate = self.trainer.jitted()
        self.carry: FusedCarry = init(jax.random.PRNGKey(config.seed), self.levels)
        log.info(
            "network %s, %s parameters:\n%s",
            config.network.kind,
            f"{sum(x.size for x in jax.tree.leaves(self.carry.train.params)):,}",
            describe_parameters(self.carry.train.params),
        )
        self.update = 0
        self.guard = NonFiniteGuard(config.ppo)
        self.init_from: dict[str, Any] = {}
        """Where the starting policy came from, when fine-tuning (written into every checkpoint's counters)."""
        if resume:
            _report(self.on_phase, "restoring the newest checkpoint")
            self._restore()
        elif init_from is not None:
            _report(self.on_phase, f"reading the starting policy of {init_from}")
            self._start_from_policy(init_from)
        log.info("compiling the training step (%s envs x %s steps) ...", config.ppo.num_envs, config.ppo.num_steps)
        _report(self.on_phase, f"compiling the training step ({config.ppo.num_envs} envs x {config.ppo.num_steps} "
                "steps)")
        start = time.perf_counter()
        # Lowered from shapes alone: a carry restored from a checkpoint holds arrays committed to a device, which
        # would otherwise put sharding annotations in the program, so that a resumed or fine-tuned run missed the
        # compilation cache that a fresh run of the same config filled. The compiled program runs on either.
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), self.carry)
        self._iterate = compile_once(iterate.lower(abstract, self.levels), "the training step")
        self.compile_s = time.perf_counter() - start
        log.info("compiled the training step in %.1f s (%s envs x %s steps)", self.compile_s,
                 config.ppo.num_envs, config.ppo.num_steps)
        try:
            check_fits(self._iterate, "the training step", config.ppo.num_envs, config.ppo.num_steps)
        except DoesNotFit as err:
            self.checkpoints.close()
            raise RunError(str(err)) from None
        self.target = self.trainer.num_updates
        self.eval_sets = None
        if config.eval.every_updates and config.eval.attempts:
            self.eval_sets = _eval_sets(config, self.agent.spec.sizes, self.names, self.levels)
        if stop_after_updates is not None:
            self.target = min(self.target, self.update + stop_after_updates)

    def _restore(self) -> None:
        """Resume exactly from a fused checkpoint; or, from a checkpoint that holds only a policy (`train`: one
        written by `impulse import-kinetix` or by a distributed run's learner), go on training that policy on
        freshly reset environments (and a fresh curriculum)."""
        if self.checkpoints.latest_step() is None:
            raise RunError(f"nothing to resume: {self.checkpoints.nothing_usable()}")
        full = fused_checkpoint_items(self.carry)

        def templates(held: frozenset[str]) -> dict[str, Any]:
            # Chosen per checkpoint tried: an older one (the newest being corrupt) may hold other items.
            return {TRAIN: full[TRAIN]} if held == {TRAIN} else full

        try:
            restored = self.checkpoints.restore(templates)
        except CheckpointError as err:
            raise RunError(str(err)) from err
        items, counters = restored.items, restored.counters
        try:
            refuse_non_finite(items[TRAIN].params, f"to resume from checkpoint {restored.step}")
        except NonFiniteParameters as err:
            raise RunError(f"{err}: it was written before Impulse refused such parameters; resume from an older "
                           "checkpoint (move the newer ones out of the checkpoints folder)") from None
        self.update = int(counters["update"])
        self.guard.skipped = int(counters.get(SKIPPED_COLUMN, 0))
        self.init_from = fine_tuning_origin(counters)
        if set(items) == {TRAIN}:
            self.carry = self.carry._replace(train=items[TRAIN])
            source = counters.get("imported_from", "a distributed run's learner")
            log.info("started from the policy of checkpoint %d (update %d, from %s) on fresh environments: the "
                     "checkpoint holds no environment state", restored.step, self.update, source)
            return
        self.carry = fused_carry_from_items(items)
        log.info("resumed from checkpoint %d (update %d, %s env steps)", restored.step,
                 self.update, f"{counters['env_steps']:,}")

    def _start_from_policy(self, source: Path) -> None:
        """Fine-tuning: the network parameters of `source`'s newest intact checkpoint (a run directory of either
        mode, or a shipped agent), with this run's fresh optimiser, environments and curriculum, from update 0."""
        try:
            start = read_starting_policy(source, self.carry.train, self.config.checkpoint)
            refuse_non_finite(start.params, "to start from its policy")
        except (CheckpointError, NonFiniteParameters) as err:
            raise RunError(f"--init-from {source}: {err}") from err
        self.carry = self.carry._replace(train=self.carry.train._replace(params=start.params))
        self.init_from = start.origin

    @property
    def env_steps(self) -> int:
        return self.update * self.steps_per_update

    def start(self) -> None:
        """Nothing left: construction compiled the training step and checked that it fits, so that a refusal
        comes before the run directory's loop starts."""

    def progress(self) -> Progress:
        return Progress(env_steps_done=self.env_steps, updates_done=self.update,
                        total_env_steps=self.trainer.num_updates * self.steps_per_update)

    def finished(self) -> bool:
        return self.update >= self.target

    def cycle(self) -> CycleReport:
        self.guard.check()  # NonFiniteUpdates: too many skipped updates in a row
        start = time.perf_counter()
        self.carry, metrics = self._iterate(self.carry, self.levels)
        metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
        self.update += 1
        self.guard.note(self.update, metrics)
        metrics.update(self.guard.columns())
        metrics["steps_per_s"] = self.steps_per_update / (time.perf_counter() - start)
        if self.carry.curriculum is not None:
            metrics.update(self.curriculum_metrics())
        if self.eval_sets is not None and self.update % self.config.eval.every_updates == 0:
            metrics.update(self.evaluation())
        return CycleReport(env_steps=self.steps_per_update, updates=1, metrics=metrics)

    def evaluation(self) -> dict[str, float]:
        """The current policy scored on the evaluation sets, as the evaluator process scores a distributed run's:
        the `eval/...` columns of metrics.jsonl."""
        config = self.config
        assert self.eval_sets is not None
        _report(self.on_phase, evaluating_phase(len(self.eval_sets.names), config.eval.attempts))
        scored = score_policy(self.agent, self.carry.train.params, self.trainer.env_params, self.eval_sets,
                              jax.random.PRNGKey(config.seed + 1 + self.update), config.eval.attempts)
        _report(self.on_phase, "training")
        log.info("update %d: evaluation mean solve rate %.0f%%%s", self.update, 100 * scored.mean,
                 "".join(f", {group} {rate:.0%}" for group, rate in scored.groups.items()))
        return evaluation_columns(scored.table, scored.groups, self.update)

    def curriculum_metrics(self) -> dict[str, float]:
        """A few buffer statistics for metrics.jsonl (`curriculum.stats.metric_columns`)."""
        return metric_columns(buffer_summary(self.carry.curriculum, self.agent.spec.sizes, self.update))

    def save(self, summary: dict[str, float]) -> None:
        refuse_non_finite(self.carry.train.params, f"checkpoint {self.update}")
        counters = {"update": self.update, "env_steps": self.env_steps, SKIPPED_COLUMN: self.guard.skipped,
                    **self.init_from, **summary}
        self.checkpoints.save(self.update, fused_checkpoint_items(self.carry), counters, self.config_toml,
                              solve_rate=summary.get("solve_rate"))

    def close(self) -> None:
        self.checkpoints.close()

    def evaluate_at_end(self, on_phase: PhaseReport | None = None) -> dict[str, dict[str, float]] | None:
        """Scores on the evaluation levels once the whole run is done (written to eval.json), else None;
        `on_phase` is told when the evaluation starts."""
        if self.update < self.trainer.num_updates:
            return None
        return final_evaluation(self.config, self.agent, self.trainer.env_params, self.carry.train.params,
                                self.run_dir, on_phase=on_phase)


def final_evaluation(config: TrainingSetup, agent: Agent, env_params: EnvParams, params: Any, run_dir: Path,
                     on_phase: PhaseReport | None = None) -> dict[str, dict[str, float]] | None:
    """Scores of `params` on the run's evaluation levels (`eval.levels`, else the training levels, else the
    hand-made set), logged as a table and written to eval.json; None when evaluation is off or has no levels.
    `on_phase` is told when it loads the levels and when it evaluates them."""
    if config.eval.attempts <= 0:
        return None
    _report(on_phase, "loading the evaluation levels")
    names, levels = _levels(config, agent.spec.sizes)
    sets = _eval_sets(config, agent.spec.sizes, names, levels)
    if sets is None or not sets.names:
        return None
    log.info("final evaluation: %d levels x %d attempts (compiling, then %s episodes) ...", len(sets.names),
             config.eval.attempts, f"{len(sets.names) * config.eval.attempts:,}")
    _report(on_phase, evaluating_phase(len(sets.names), config.eval.attempts))
    start = time.perf_counter()
    scored = score_policy(agent, params, env_params, sets, jax.random.PRNGKey(config.seed + 1),
                          config.eval.attempts)
    log.info("final evaluation done in %.0f s", time.perf_counter() - start)
    (run_dir / "eval.json").write_text(json.dumps(scored.table, indent=2))
    log.info("evaluation over %d attempts per level:\n%s", config.eval.attempts,
             format_scores(scored.table, scored.groups))
    return scored.table


def restore_policy(config: TrainingSetup, run_dir: Path, step: int | None = None,
                   trainer: FusedTrainer | None = None) -> Restored:
    """The `train` item (the policy) of a run's checkpoint, newest intact unless `step`, whichever mode wrote it;
    `trainer` from `build(config)` when the caller has it already. A reader: a corrupt newer checkpoint is skipped
    and left where it is (the run, or the shipped agent, is not this process's to change)."""
    if trainer is None:
        trainer = build(config)[0]
    template = jax.eval_shape(trainer.init_train, jax.random.PRNGKey(config.seed))
    with Checkpointer(run_dir / config.checkpoint.directory, config.checkpoint) as checkpoints:
        try:
            return checkpoints.restore({TRAIN: template}, step, set_aside=False)
        except CheckpointError as err:
            raise RunError(str(err)) from err


def export_policy(config: TrainingSetup, run_dir: Path, out_dir: Path, config_toml: str, step: int | None = None,
                  note: dict[str, Any] | None = None) -> dict[str, Any]:
    """The policy of a run's checkpoint (newest intact unless `step`) written alone into `out_dir`'s checkpoints:
    a small run directory that `impulse eval`, `impulse train --init-from` and `--resume` read (the latter two go
    on training it on fresh environments). Returns the counters written: the source's, with `note` added."""
    restored = restore_policy(config, run_dir, step)
    try:
        refuse_non_finite(restored.items[TRAIN].params, f"to export checkpoint {restored.step}")
    except NonFiniteParameters as err:
        raise RunError(str(err)) from None
    counters = {key: value for key, value in restored.counters.items() if key in ("update", "env_steps",
                                                                               "policy_version", "solve_rate")}
    counters.update(note or {}, exported_from_step=restored.step)
    with Checkpointer(out_dir / config.checkpoint.directory, config.checkpoint) as exported:
        if exported.latest_step() is not None:
            raise RunError(f"{out_dir} already holds a checkpoint; export into a new directory")
        exported.save(restored.step, {TRAIN: restored.items[TRAIN]}, counters, config_toml)
    return counters


def fused_checkpoint_items(carry: FusedCarry) -> dict[str, Any]:
    """A fused carry as checkpoint items: `train`, `envs` (environments and the iteration key) and, on random
    levels, `curriculum` (its whole state, knobs included)."""
    items = {TRAIN: carry.train, ENVS: {"rollout": carry.envs, "key": carry.key}}
    if carry.curriculum is not None:
        items[CURRICULUM] = carry.curriculum
    return items


def fused_carry_from_items(items: dict[str, Any]) -> FusedCarry:
    return FusedCarry(items[TRAIN], items[ENVS]["rollout"], items[ENVS]["key"], items.get(CURRICULUM))


def evaluate_run(
    config: TrainingSetup,
    run_dir: Path,
    step: int | None = None,
    levels: str | None = None,
    attempts: int | None = None,
    seed: int = 0,
    greedy: bool = False,
    recorder: Callable[[list[str], RecordedEpisodes, int], None] | None = None,
    on_phase: PhaseReport | None = None,
    on_level: LevelScored | None = None,
) -> dict[str, dict[str, float]]:
    """Scores per level of a run's checkpoint (newest unless `step`), on `levels` (default: as after training).
    `recorder(names, episodes, policy_version)`, if given, receives one more episode per level, recorded for
    drawing (`learner.evaluate.record_episodes`). `on_phase` is told of each phase as it starts (they are logged
    too), `on_level` of each level's score (`score_policy`)."""
    _report(on_phase, "building the environment and the network")
    trainer, agent, names, train_levels = build(config)
    sizes = agent.spec.sizes
    if levels:
        try:
            sets = load_level_sets(levels, sizes)
        except LevelSetError as err:
            raise RunError(str(err)) from err
    else:
        sets = _eval_sets(config, sizes, names, train_levels)
        if sets is None:
            raise RunError("no evaluation levels: pass --levels")
    _report(on_phase, f"restoring the policy of {run_dir}")
    restored = restore_policy(config, run_dir, step, trainer)
    items, counters = restored.items, restored.counters
    params = items[TRAIN].params
    attempts = attempts or config.eval.attempts
    phase = evaluating_phase(len(sets.names), attempts)
    log.info("%s (compiling, then %s episodes) ...", phase, f"{len(sets.names) * attempts:,}")
    _report(on_phase, phase)
    started = time.perf_counter()
    scored = score_policy(agent, params, trainer.env_params, sets, jax.random.PRNGKey(seed), attempts, greedy=greedy,
                          on_level=on_level)
    log.info("evaluated %d levels in %.1f s (compiling included)", len(sets.names), time.perf_counter() - started)
    if recorder is not None:
        phase = (f"playing one more episode per level to record ({len(sets.names)} levels, up to "
                 f"{agent.spec.max_timesteps} steps each)")
        log.info("%s ...", phase)
        _report(on_phase, phase)
        episodes = record_episodes(agent, params, trainer.env_params, sets.levels, jax.random.PRNGKey(seed + 1),
                                   greedy)
        recorder(list(sets.names), episodes, int(counters.get("policy_version", counters.get("update", 0))))
    return scored.table
