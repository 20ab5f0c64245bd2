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

    <root>/learner/weights/policy       weights broadcast (cached for late joiners under .../@adv/pub/...)
    <root>/learner/weights/latest       weights queryable (fallback)
    <root>/learner/credit/<actor>       acknowledgements (credits) for one actor
    <root>/curriculum/levels/sample     level-batch queryable
    <root>/curriculum/knobs             live knobs queryable (`impulse curriculum get|set`)
    <root>/curriculum/inspect           buffer report queryable (`impulse curriculum inspect`)
    <root>/curriculum/inject            level injection queryable (`impulse curriculum inject`, the studio)
    <root>/actor/traj/<actor>           trajectory batches
    <root>/actor/results/<actor>        per-level results
    <root>/actor/played/<actor>         the level batch an actor plays next (only while a recorder listens)
    <root>/evaluator/results/<id>       evaluations of the learner's policy on level sets
    <root>/<role>/status/<id>           status lines (every process)
    <root>/<role>/alive/<id>            liveliness tokens (every process)
    <root>/learner/alive/instance-<n>   the learner process's instance token (its nonce, also in its weights)
"""

from __future__ import annotations

from dataclasses import dataclass

SCHEMA_MAJOR = 2
"""Major version of the wire format. Incompatible changes bump it, which changes every key (`v1` -> `v2`).
2: keys under each role's own prefix, no sender name in frames, digests on control frames. A change confined to
one message family's arrays versions that family instead, inside its frames (the trajectories' formats:
`bus.trajectories`), so that frames of another format still arrive and are refused and counted."""

PREFIX = "impulse"
"""First chunk of every key the system uses."""

LEARNER = "learner"
CURRICULUM = "curriculum"
ACTOR = "actor"
EVALUATOR = "evaluator"
OPERATOR = "operator"
"""The `<role>` chunks of the roles whose messages this module names keys for; the operator is any command-line
tool, the launcher or a watcher. What each role may ask and hear, and the roles added beside them, are
`bus.roles`; across machines each role has credentials of its own (`bus.router`)."""

RECORDER = "recorder"
"""The recorder's `<role>` chunk: it publishes only its status and liveliness, which the learner hears."""

STATUS = "status"
ALIVE = "alive"
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

    # -- the learner's --------------------------------------------------------------------------------------

    @property
    def weights_policy(self) -> str:
        """Policy weights broadcast by the learner, cached so that late joiners get the newest."""
        return self.own(LEARNER, "weights", "policy")

    @property
    def weights_latest(self) -> str:
        """Queryable fallback for pulling the newest weights."""
        return self.own(LEARNER, "weights", "latest")

    def credit(self, actor: str) -> str:
        """Credits the learner grants to one actor (how many trajectories it may have in flight)."""
        return self.own(LEARNER, "credit", check_name(actor, "actor id"))

    # -- the curriculum's -----------------------------------------------------------------------------------

    @property
    def levels_sample(self) -> str:
        """Queryable of the curriculum: actors pull batches of levels from it."""
        return self.own(CURRICULUM, "levels", "sample")

    @property
    def curriculum_knobs(self) -> str:
        """Queryable of the curriculum: read or change its live knobs (`impulse curriculum get|set`)."""
        return self.own(CURRICULUM, "knobs")

    @property
    def curriculum_inspect(self) -> str:
        """Queryable of the curriculum: its buffer statistics and levels (`impulse curriculum inspect`)."""
        return self.own(CURRICULUM, "inspect")

    @property
    def curriculum_inject(self) -> str:
        """Queryable of the curriculum: put a level a person sends into its buffer (`impulse curriculum inject`)."""
        return self.own(CURRICULUM, "inject")

    # -- the actors' ----------------------------------------------------------------------------------------

    def traj(self, actor: str) -> str:
        """Trajectories published by one actor to the learner."""
        return self.own(ACTOR, "traj", check_name(actor, "actor id"))

    @property
    def traj_all(self) -> str:
        """Pattern matching every actor's trajectories (the learner's subscription)."""
        return self.own(ACTOR, "traj", "*")

    def levels_results(self, actor: str) -> str:
        """Per-level results published by one actor to the curriculum."""
        return self.own(ACTOR, "results", check_name(actor, "actor id"))

    @property
    def levels_results_all(self) -> str:
        """Pattern matching every actor's level results (the curriculum's subscription)."""
        return self.own(ACTOR, "results", "*")

    def levels_played(self, actor: str) -> str:
        """The level batch one actor plays next, published for a recorder."""
        return self.own(ACTOR, "played", check_name(actor, "actor id"))

    @property
    def levels_played_all(self) -> str:
        """Pattern matching every actor's played levels (the recorder's subscription)."""
        return self.own(ACTOR, "played", "*")

    # -- the evaluator's ------------------------------------------------------------------------------------

    def evaluation(self, ident: str) -> str:
        """Evaluations of the learner's policies published by one evaluator."""
        return self.own(EVALUATOR, "results", check_name(ident, "id"))

    @property
    def evaluations_all(self) -> str:
        """Pattern matching every evaluator's results (the learner's subscription)."""
        return self.own(EVALUATOR, "results", "*")

    # -- every process's ------------------------------------------------------------------------------------

    def status(self, role: str, ident: str) -> str:
        """Status lines published by one process."""
        return self.own(role, STATUS, check_name(ident, "id"))

    def status_pattern(self, role: str | None = None) -> str:
        """Pattern matching the status lines of one role, or of every process when `role` is None."""
        return f"{self.root}/{'*' if role is None else check_role(role)}/{STATUS}/*"

    def parse_status(self, key: str) -> tuple[str, str]:
        """(role, ident) of a status key of this run; ValueError if `key` is not one."""
        return self._parse(key, STATUS, "status")

    def alive(self, role: str, ident: str) -> str:
        """Liveliness token of one process: present while its session is up."""
        return self.own(role, ALIVE, check_name(ident, "id"))

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
