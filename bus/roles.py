"""What each role of a run may do on a router with access control: the role's part of the protocol, as data.

A `Role` names the keys (under a run's root `impulse/<run>/v2/`, any run) that a process of that role may query
(`asks`) and whose puts the router delivers to it (`hears`), by route name from the route table
(`bus.routes.patterns`). Every role also publishes under its own prefix and nothing else, and hears every status
line; `bus.router.access_rules` turns a run's roles into Zenoh's rules.

The roles of the protocol itself (learner, curriculum, actor, and operator for command-line tools, the launcher
and watchers) are declared here. A role added later (the evaluator, the recorder) declares its `Role` beside the
row of the command that runs it (`deploy/commands/__init__.py`; `impulse router` gathers them from that table), so
adding a role does not edit the bus.
"""

from __future__ import annotations

from dataclasses import dataclass

from impulse.bus.keys import check_name
from impulse.bus.routes import ACTOR, CURRICULUM, LEARNER, OPERATOR, ROUTE, patterns

WEIGHTS_CACHE = f"{ROUTE['weights'].pattern}/@adv/**"
"""The advanced publisher's cache of the learner's weights for late joiners; `**` does not match an `@` chunk,
hence a pattern of its own."""

FOLLOWS_WEIGHTS = (f"{LEARNER}/weights/**", WEIGHTS_CACHE)
"""What a role that follows the learner's weights asks: every key of the weights routes (`weights`, the broadcast,
and `weights_latest`, the queryable) and the late joiners' cache."""

LEARNER_BROADCASTS = (f"{LEARNER}/**",)
"""What a role that follows the learner hears: its weights, credits and everything else it publishes."""


@dataclass(frozen=True)
class Role:
    """One role of a run's processes: its key prefix and what the router lets it ask and hear."""

    name: str
    """The `<role>` chunk of its keys, and the certificate common name and password user it presents."""
    asks: tuple[str, ...] = ()
    """Key patterns under the run's root it may query."""
    hears: tuple[str, ...] = ()
    """Key patterns under the run's root whose puts reach it, beyond every process's status lines."""
    answers: bool = False
    """Whether puts and queries under its own prefix reach it (a role that declares queryables)."""

    def __post_init__(self) -> None:
        check_name(self.name, "role")


LEARNER_ROLE = Role(LEARNER, hears=patterns("traj", "evaluations"), answers=True)
CURRICULUM_ROLE = Role(CURRICULUM, asks=FOLLOWS_WEIGHTS, hears=(*patterns("levels_results"), *LEARNER_BROADCASTS),
                       answers=True)
ACTOR_ROLE = Role(ACTOR, asks=(*FOLLOWS_WEIGHTS, *patterns("levels_sample")), hears=LEARNER_BROADCASTS)
OPERATOR_ROLE = Role(OPERATOR, asks=patterns("curriculum_knobs", "curriculum_inspect", "curriculum_inject"))
PROTOCOL_ROLES = (LEARNER_ROLE, CURRICULUM_ROLE, ACTOR_ROLE, OPERATOR_ROLE)
"""The roles the protocol cannot run without."""
