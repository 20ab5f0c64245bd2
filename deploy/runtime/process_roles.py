"""The processes `impulse launch` starts, as one registry: every other part of the launcher derives from it.

One `ProcessRole` per kind of process a run on one machine has (the Rerun viewer, the learner, the curriculum
service, the evaluator, the recorder, the actors), in the order the launcher starts them. An entry says how many
processes of it a run starts (none when its config section leaves it off), the command line of each start and
restart, which bus role's credentials it presents, how the launch's first line names it, how the status display
reads its status, and what the run does when the launcher gives up on it (`Kind`) or stops (`stop_stage`).

Derived from it: the children (`launch_children`), the actors the run needs one of (`group`), the stop order
(`stop_stages`), the rule of giving up (`needed_after_giving_up`), the roles preflight checks credentials for
(`credential_roles`), the launch's summary line (`launch_summary`), how many processes share the host's memory
(`jax_processes`) and the display's reading of each row (`parts_by_child`). A new role is one entry here, beside
its service module, its config section and its command module.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from impulse.bus.keys import ACTOR, CURRICULUM, EVALUATOR, LEARNER, RECORDER
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.status_display import (
    Part,
    StatusParts,
    actor_parts,
    curriculum_parts,
    evaluator_parts,
    learner_parts,
    recorder_parts,
)
from impulse.deploy.runtime.supervisor import Child


class Kind(Enum):
    """What the run does when the launcher gives up restarting a process of a role."""

    CRITICAL = "critical"
    """The run cannot go on without it: the launcher stops the run (the learner, the curriculum service)."""
    FOLLOWER = "follower"
    """One of a group the run needs at least one of: the run stops once the launcher gave up on all (the actors)."""
    SIDECAR = "sidecar"
    """The run goes on without it (the evaluator, the recorder, the viewer)."""


@dataclass(frozen=True)
class LaunchPlan:
    """What a launch decided before starting anything, which the command lines are built from."""

    config: RunConfig
    run_dir: Path
    resume: bool
    """`--resume`: the learner's first start resumes too."""
    init_from: Path | None = None
    """`--init-from`: the policy a learner without checkpoints of its own starts from (on restarts too)."""
    record: Path | None = None
    """`--record FILE.rrd`."""
    view: bool = False
    """`--view`: a viewer is started (else, with `record`, a headless recording server)."""

    @property
    def streams(self) -> bool:
        """Whether the processes stream to a Rerun server the launch starts."""
        return self.view or self.record is not None


Argv = Callable[[LaunchPlan, int, bool], list[str]]
"""A role's command line from the plan, the process's index among its role's and whether this start is a restart."""


@dataclass(frozen=True)
class ProcessRole:
    """One kind of process a launch starts."""

    name: str
    """The process's name in logs, the status display and its log file; a role of several processes names them
    `<name>-<index>`. The name is also the bus ident its status lines are published under."""
    kind: Kind
    stop_stage: float
    """When it is stopped on the way out: lower stages first, one stage at a time."""
    count: Callable[[LaunchPlan], int]
    """How many processes of this role the run starts (0: none)."""
    argv: Argv
    bus_role: str | None
    """The bus role whose credentials it presents (None: it is not on the bus)."""
    describe: Callable[[RunConfig], str] | None
    """Its words in the launch's first line ("curriculum (sfl)"); None: not named there."""
    parts: StatusParts | None
    """How the status display reads its status; None: it publishes none (the viewer)."""
    runs_jax: bool = True
    """Whether it runs JAX programs sized by the batch (which share the host's memory on a CPU)."""
    several: bool = False
    """Whether it is a role of several processes (named `<name>-<index>`)."""
    stop_timeout_s: float = 20.0
    """How long its stop waits before it kills."""
    stop_note: str | None = None
    """Logged when the launcher stops it, if it is still running."""
    restart_note: str = ""
    """Said after "restarting it in N s" (how it comes back)."""
    ends_with_run: bool = False
    """Whether it exits 0 once the learner has finished the run, and is then not restarted (the learner's
    followers); a clean exit of another role's process is a restart like any exit."""

    def child_name(self, index: int) -> str:
        return f"{self.name}-{index}" if self.several else self.name

    def plays(self, child_name: str) -> bool:
        """Whether the process called `child_name` is one of this role's."""
        if not self.several:
            return child_name == self.name
        prefix, _, index = child_name.rpartition("-")
        return prefix == self.name and index.isdigit()


def service_argv(*command: str, plan: LaunchPlan, extra: tuple[str, ...] = ()) -> list[str]:
    """`python -m impulse.deploy.cli COMMAND... --run RUN_DIR EXTRA...` with this interpreter."""
    return [sys.executable, "-m", "impulse.deploy.cli", *command, "--run", str(plan.run_dir), *extra]


def _viewer_argv(plan: LaunchPlan, index: int, restart: bool) -> list[str]:
    record = ["--record", str(plan.record)] if plan.record is not None else []
    headless = [] if plan.view else ["--headless"]
    return [sys.executable, "-m", "impulse.deploy.cli", "view", str(plan.run_dir), *record, *headless]


def _learner_argv(plan: LaunchPlan, index: int, restart: bool) -> list[str]:
    # On a restart too: a learner that died before its first checkpoint starts from the same policy again.
    fine_tune = ("--init-from", str(plan.init_from)) if plan.init_from is not None else ()
    resume = ("--resume",) if restart or plan.resume else ()
    return service_argv("learner", plan=plan, extra=(*fine_tune, *resume))


def _lag_of(name: str, statuses: Mapping[str, Any]) -> int | None:
    """The policy lag the learner last reported for the actor `name`."""
    learner = statuses.get(LEARNER_ROLE.name)
    lags = learner.get("actor_lag", {}) if isinstance(learner, dict) else {}
    return lags.get(name) if isinstance(lags, dict) else None


def _alone(read: Callable[[dict[str, Any]], list[Part]]) -> StatusParts:
    """A role's reading of its status that needs nothing but the status."""
    return lambda name, status, statuses: read(status)


VIEWER_ROLE = ProcessRole(
    "viewer", Kind.SIDECAR, stop_stage=4, count=lambda plan: int(plan.streams), argv=_viewer_argv, bus_role=None,
    describe=None, parts=None, runs_jax=False)
"""`impulse view`: last to stop, so the others' final metrics reach it."""
LEARNER_ROLE = ProcessRole(
    LEARNER, Kind.CRITICAL, stop_stage=3, count=lambda plan: 1, argv=_learner_argv, bus_role=LEARNER,
    describe=lambda config: "learner", parts=_alone(learner_parts), stop_timeout_s=180.0,
    stop_note="stopping the learner (it writes a final checkpoint)", restart_note=" with --resume")
CURRICULUM_ROLE = ProcessRole(
    CURRICULUM, Kind.CRITICAL, stop_stage=2, count=lambda plan: int(plan.config.uses_curriculum_service),
    # Always --resume: its own checkpoints hold every buffered level (none yet on a fresh run).
    argv=lambda plan, index, restart: service_argv("curriculum", "serve", plan=plan, extra=("--resume",)),
    bus_role=CURRICULUM, describe=lambda config: f"curriculum ({config.curriculum.method})",
    parts=_alone(curriculum_parts))
"""Stopped after the recorder and the actors; it writes a final checkpoint of its buffer."""
EVALUATOR_ROLE = ProcessRole(
    EVALUATOR, Kind.SIDECAR, stop_stage=0, count=lambda plan: int(bool(plan.config.evaluator.levels)),
    argv=lambda plan, index, restart: service_argv("evaluator", plan=plan), bus_role=EVALUATOR,
    describe=lambda config: f"evaluator ({config.evaluator.levels})", parts=_alone(evaluator_parts),
    ends_with_run=True)
"""Stopped first with the actors: it follows the learner."""
RECORDER_ROLE = ProcessRole(
    RECORDER, Kind.SIDECAR, stop_stage=1, count=lambda plan: int(bool(plan.config.recorder.path)),
    argv=lambda plan, index, restart: service_argv("recorder", plan=plan), bus_role=RECORDER,
    describe=lambda config: f"recorder ({config.recorder.path})", parts=_alone(recorder_parts), runs_jax=False,
    ends_with_run=True)
"""Started before the actors, so that it hears their first batches; stopped after them: it writes what they sent."""
ACTOR_ROLE = ProcessRole(
    ACTOR, Kind.FOLLOWER, stop_stage=0, count=lambda plan: plan.config.actors.num_actors,
    argv=lambda plan, index, restart: service_argv("actor", plan=plan, extra=("--index", str(index))),
    bus_role=ACTOR, several=True, ends_with_run=True,
    describe=lambda config: f"{config.actors.num_actors} actor{'s' if config.actors.num_actors != 1 else ''}",
    parts=lambda name, status, statuses: actor_parts(status, _lag_of(name, statuses)))

PROCESS_ROLES: tuple[ProcessRole, ...] = (VIEWER_ROLE, LEARNER_ROLE, CURRICULUM_ROLE, EVALUATOR_ROLE, RECORDER_ROLE,
                                          ACTOR_ROLE)
"""Every role a launch may start, in the order it starts them."""


def role_of(child_name: str, roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> ProcessRole:
    """The role the process called `child_name` plays."""
    for role in roles:
        if role.plays(child_name):
            return role
    raise KeyError(f"no process role plays {child_name!r}")


def launch_children(plan: LaunchPlan, roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> list[Child]:
    """The processes of this launch, in start order, each logging to `RUN_DIR/logs/<name>.log`."""
    children = []
    for role in roles:
        for index in range(role.count(plan)):
            name = role.child_name(index)
            children.append(Child(name, lambda restart, r=role, i=index: r.argv(plan, i, restart),
                                  plan.run_dir / "logs" / f"{name}.log"))
    return children


def group(children: list[Child], kind: Kind, roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> list[Child]:
    """The children whose role is of `kind` (`Kind.FOLLOWER`: the actors the run needs at least one of)."""
    return [child for child in children if role_of(child.name, roles).kind is kind]


def stop_stages(children: list[Child], roles: tuple[ProcessRole, ...] = PROCESS_ROLES
                ) -> list[tuple[ProcessRole, list[Child]]]:
    """The order the launcher stops its children in: one entry per stage, lowest first, with a role of the stage
    (whose timeout and note it uses; a stage of several roles takes the longest timeout's) and its children."""
    stages: dict[int, list[Child]] = {}
    for child in children:
        stages.setdefault(role_of(child.name, roles).stop_stage, []).append(child)
    ordered = []
    for stage in sorted(stages):
        members = {role_of(child.name, roles).name: role_of(child.name, roles) for child in stages[stage]}
        lead = max(members.values(), key=lambda role: role.stop_timeout_s)
        ordered.append((lead, stages[stage]))
    return ordered


def needed_after_giving_up(child: Child, children: list[Child], roles: tuple[ProcessRole, ...] = PROCESS_ROLES
                           ) -> list[Child]:
    """The children without which the run cannot go on, now that the launcher gave up on `child`: itself if its
    role is critical, every follower once all of them have been given up on, else none (it goes on)."""
    kind = role_of(child.name, roles).kind
    if kind is Kind.CRITICAL:
        return [child]
    if kind is Kind.FOLLOWER:
        followers = group(children, Kind.FOLLOWER, roles)
        return followers if all(follower.gave_up for follower in followers) else []
    return []


def credential_roles(plan: LaunchPlan, roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> list[str]:
    """The bus roles whose credentials this launch's processes present."""
    return [role.bus_role for role in roles if role.bus_role is not None and role.count(plan) > 0]


def launch_summary(plan: LaunchPlan, roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> list[str]:
    """The launch's first line's names of what it starts ("learner", "curriculum (sfl)", "2 actors")."""
    return [role.describe(plan.config) for role in roles if role.describe is not None and role.count(plan) > 0]


def jax_processes(children: list[Child], roles: tuple[ProcessRole, ...] = PROCESS_ROLES) -> int:
    """How many of the children run JAX programs sized by the batch, sharing the host's memory on a CPU."""
    return sum(role_of(child.name, roles).runs_jax for child in children)


def parts_by_child(children: list[Child], roles: tuple[ProcessRole, ...] = PROCESS_ROLES
                   ) -> dict[str, StatusParts | None]:
    """Each child's role's reading of its status, for `status_display.status_block`."""
    return {child.name: role_of(child.name, roles).parts for child in children}
