"""Key expressions of one run: every message of the system is published under `impulse/<run>/v2/<role>/...`.

The run id and the wire-schema major version sit in the key, so two runs sharing a hub, or a process built
against an incompatible wire format, never even match each other's subscriptions. Building the keys in one place
keeps publishers and subscribers from drifting apart by a typo.

**Each role publishes only under its own prefix** `impulse/<run>/v2/<role>/`: the learner its weights, credits
and status; the curriculum its answers to level and knob queries and its status; an actor its trajectories, level
results and status; the operator (command-line tools, the launcher, status watchers) only its status and
liveliness. A router with access control (`bus.router.access_rules`) lets each role's credentials publish there and
nowhere else, so a receiver knows who sent a message from the key it arrived on, which the router guarantees, and
never from a name the message gives itself. The `<actor>` chunk of an actor's keys is not guaranteed (all actors
share one credential): it tells actors apart, it does not authenticate one.

Every key is one route's (`bus.routes.ROUTES`: the sender's prefix, the route's chunks, and for a per-sender route
the sender's id), so the layout is written in one place; `Keys.key(route, ...)` builds any of them, and the named
methods below are the ones the code uses.
"""

from __future__ import annotations

from dataclasses import dataclass

from impulse.bus.codec import SCHEMA_MAJOR  # re-exported: the key carries it too
from impulse.bus.routes import (  # the role chunks, re-exported: most callers take them from here
    ACTOR,
    ALIVE,
    ANY_ROLE,
    CURRICULUM,
    EVALUATOR,
    LEARNER,
    OPERATOR,
    RECORDER,
    ROUTE,
    STATUS,
)

__all__ = ["ACTOR", "ALIVE", "CURRICULUM", "EVALUATOR", "INSTANCE", "LEARNER", "OPERATOR", "PREFIX", "RECORDER",
           "SCHEMA_MAJOR", "STATUS", "Keys", "check_name", "check_role"]

PREFIX = "impulse"
"""First chunk of every key the system uses."""

INSTANCE = "instance-"
"""Prefix of the learner's second liveliness token, `<root>/learner/alive/instance-<nonce>`: the random nonce one
learner process draws at start and puts in every weights frame, so that a follower adopts weights only from the
learner whose token it follows (`Keys.learner_instance`, `actors.follow`)."""

_FORBIDDEN = frozenset("/*$#?@")


def check_name(name: str, what: str) -> str:
    """Return `name` if it can be one chunk of a key expression, else raise ValueError naming the problem.

    Run ids, actor ids and role names become single key chunks; a `/` would split them, `*` and `$` would turn
    them into wildcards that match other processes' keys, `@` starts zenoh's reserved chunks, and `#`, `?` and
    whitespace are not allowed in keys. `what` says which name it is ("run id", "actor id", ...) for the error.
    """
    if not isinstance(name, str):
        raise ValueError(f"{what} must be a string, got {type(name).__name__}")
    if not name:
        raise ValueError(f"{what} is empty")
    bad = sorted({ch for ch in name if ch in _FORBIDDEN or ch.isspace()})
    if bad:
        raise ValueError(f"{what} {name!r} contains {', '.join(repr(ch) for ch in bad)}, not allowed in a key chunk")
    return name


def check_role(role: str) -> str:
    """Return `role` if it can be the `<role>` chunk of a key, else raise ValueError. Which roles a router lets
    publish is its access control's business (`bus.roles`), not this module's."""
    return check_name(role, "role")


@dataclass(frozen=True)
class Keys:
    """The key expressions of one run, under `impulse/<run>/v2/` (see the module docstring for the layout)."""

    run: str

    def __post_init__(self) -> None:
        check_name(self.run, "run id")

    @property
    def root(self) -> str:
        """`impulse/<run>/v2`: the common prefix of all keys of this run."""
        return f"{PREFIX}/{self.run}/v{SCHEMA_MAJOR}"

    def own(self, role: str, *chunks: str) -> str:
        """A key under `role`'s own prefix: only `role` may publish there (where a router enforces it)."""
        return "/".join((self.root, check_role(role), *chunks))

    def key(self, route: str, sender: str | None = None, role: str | None = None) -> str:
        """The key of route `route` (`bus.routes.ROUTES`): `sender` is the sending process's id for a per-sender
        route ("*": all of them, a subscription's pattern), `role` the publishing role for a route any role
        publishes (status lines, liveliness). ValueError when one is missing or not one key chunk."""
        entry = ROUTE[route]
        publisher = entry.sender if entry.sender != ANY_ROLE else role
        if publisher is None:
            raise ValueError(f"route {route} is published by every role: say which")
        chunks = entry.topic
        if entry.per_sender:
            if sender is None:
                raise ValueError(f"route {route} has one key per sender: say whose")
            chunks = (*chunks, sender if sender == "*" else check_name(sender, "id"))
        return self.own(publisher, *chunks)

    # -- the learner's --------------------------------------------------------------------------------------

    @property
    def weights_policy(self) -> str:
        """Policy weights broadcast by the learner, cached so that late joiners get the newest."""
        return self.key("weights")

    @property
    def weights_latest(self) -> str:
        """Queryable fallback for pulling the newest weights."""
        return self.key("weights_latest")

    def credit(self, actor: str) -> str:
        """Credits the learner grants to one actor (how many trajectories it may have in flight)."""
        return self.key("credit", check_name(actor, "actor id"))

    # -- the curriculum's -----------------------------------------------------------------------------------

    @property
    def levels_sample(self) -> str:
        """Queryable of the curriculum: actors pull batches of levels from it."""
        return self.key("levels_sample")

    @property
    def curriculum_knobs(self) -> str:
        """Queryable of the curriculum: read or change its live knobs (`impulse curriculum get|set`)."""
        return self.key("curriculum_knobs")

    @property
    def curriculum_inspect(self) -> str:
        """Queryable of the curriculum: its buffer statistics and levels (`impulse curriculum inspect`)."""
        return self.key("curriculum_inspect")

    @property
    def curriculum_inject(self) -> str:
        """Queryable of the curriculum: put a level a person sends into its buffer (`impulse curriculum inject`)."""
        return self.key("curriculum_inject")

    # -- the actors' ----------------------------------------------------------------------------------------

    def traj(self, actor: str) -> str:
        """Trajectories published by one actor to the learner."""
        return self.key("traj", check_name(actor, "actor id"))

    @property
    def traj_all(self) -> str:
        """Pattern matching every actor's trajectories (the learner's subscription)."""
        return self.key("traj", "*")

    def levels_results(self, actor: str) -> str:
        """Per-level results published by one actor to the curriculum."""
        return self.key("levels_results", check_name(actor, "actor id"))

    @property
    def levels_results_all(self) -> str:
        """Pattern matching every actor's level results (the curriculum's subscription)."""
        return self.key("levels_results", "*")

    def levels_played(self, actor: str) -> str:
        """The level batch one actor plays next, published for a recorder."""
        return self.key("levels_played", check_name(actor, "actor id"))

    @property
    def levels_played_all(self) -> str:
        """Pattern matching every actor's played levels (the recorder's subscription)."""
        return self.key("levels_played", "*")

    # -- the evaluator's ------------------------------------------------------------------------------------

    def evaluation(self, ident: str) -> str:
        """Evaluations of the learner's policies published by one evaluator."""
        return self.key("evaluations", check_name(ident, "id"))

    @property
    def evaluations_all(self) -> str:
        """Pattern matching every evaluator's results (the learner's subscription)."""
        return self.key("evaluations", "*")

    # -- every process's ------------------------------------------------------------------------------------

    def status(self, role: str, ident: str) -> str:
        """Status lines published by one process."""
        return self.key("status", check_name(ident, "id"), role)

    def status_pattern(self, role: str | None = None) -> str:
        """Pattern matching the status lines of one role, or of every process when `role` is None."""
        return f"{self.root}/{'*' if role is None else check_role(role)}/{STATUS}/*"

    def parse_status(self, key: str) -> tuple[str, str]:
        """(role, ident) of a status key of this run; ValueError if `key` is not one."""
        return self._parse(key, STATUS, "status")

    def alive(self, role: str, ident: str) -> str:
        """Liveliness token of one process: present while its session is up."""
        return self.key("alive", check_name(ident, "id"), role)

    def alive_pattern(self, role: str | None = None) -> str:
        """Pattern matching the liveliness tokens of one role, or of every process when `role` is None."""
        return f"{self.root}/{'*' if role is None else check_role(role)}/{ALIVE}/*"

    def parse_alive(self, key: str) -> tuple[str, str]:
        """(role, ident) of a liveliness key of this run; ValueError if `key` is not one."""
        return self._parse(key, ALIVE, "liveliness")

    def learner_instance(self, nonce: str) -> str:
        """Liveliness token of one learner process (its start's nonce), beside its `alive(LEARNER, ...)` token."""
        return self.alive(LEARNER, INSTANCE + check_name(nonce, "learner nonce"))

    @staticmethod
    def instance_nonce(ident: str) -> str | None:
        """The nonce of a learner instance token's id (`instance-<nonce>`), or None for any other id."""
        if not ident.startswith(INSTANCE):
            return None
        return ident[len(INSTANCE):] or None

    def _parse(self, key: str, topic: str, what: str) -> tuple[str, str]:
        rest = key[len(self.root) + 1 :] if key.startswith(self.root + "/") else ""
        parts = rest.split("/")
        if len(parts) != 3 or not parts[0] or parts[1] != topic or not parts[2]:
            raise ValueError(f"{key!r} is not a {what} key of run {self.run!r} ({self.root}/<role>/{topic}/<id>)")
        return parts[0], parts[2]
