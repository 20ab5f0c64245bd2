"""Key expressions of one run: every message of the system is published under `impulse/<run>/v1/...`.

The run id and the wire-schema major version sit in the key, so two runs sharing a hub, or a process built
against an incompatible wire format, never even match each other's subscriptions. Building the keys in one place
keeps publishers and subscribers from drifting apart by a typo.
"""

from __future__ import annotations

from dataclasses import dataclass

SCHEMA_MAJOR = 1
"""Major version of the wire format. Incompatible changes bump it, which changes every key (`v1` -> `v2`)."""

PREFIX = "impulse"
"""First chunk of every key the system uses."""

LEARNER = "learner"
CURRICULUM = "curriculum"
ACTOR = "actor"
OPERATOR = "operator"
ROLES = (LEARNER, CURRICULUM, ACTOR, OPERATOR)
"""The roles of a run's processes (the `<role>` chunk of their keys); the operator is any command-line tool.
Across machines each role has credentials of its own (`bus.router`)."""

_FORBIDDEN = frozenset("/*$#?")


def check_name(name: str, what: str) -> str:
    """Return `name` if it can be one chunk of a key expression, else raise ValueError naming the problem.

    Run ids, actor ids and role names become single key chunks; a `/` would split them, `*` and `$` would turn
    them into wildcards that match other processes' keys, and `#`, `?` and whitespace are not allowed in keys.
    `what` says which name it is ("run id", "actor id", ...) for the error message.
    """
    if not isinstance(name, str):
        raise ValueError(f"{what} must be a string, got {type(name).__name__}")
    if not name:
        raise ValueError(f"{what} is empty")
    bad = sorted({ch for ch in name if ch in _FORBIDDEN or ch.isspace()})
    if bad:
        raise ValueError(f"{what} {name!r} contains {', '.join(repr(ch) for ch in bad)}, not allowed in a key chunk")
    return name


@dataclass(frozen=True)
class Keys:
    """The key expressions of one run, under `impulse/<run>/v1/`."""

    run: str

    def __post_init__(self) -> None:
        check_name(self.run, "run id")

    @property
    def root(self) -> str:
        """`impulse/<run>/v1`: the common prefix of all keys of this run."""
        return f"{PREFIX}/{self.run}/v{SCHEMA_MAJOR}"

    def traj(self, actor: str) -> str:
        """Trajectories published by one actor to the learner."""
        return f"{self.root}/traj/{check_name(actor, 'actor id')}"

    @property
    def traj_all(self) -> str:
        """Pattern matching every actor's trajectories (the learner's subscription)."""
        return f"{self.root}/traj/*"

    def credit(self, actor: str) -> str:
        """Credits the learner grants to one actor (how many trajectories it may have in flight)."""
        return f"{self.root}/credit/{check_name(actor, 'actor id')}"

    @property
    def weights_policy(self) -> str:
        """Policy weights broadcast by the learner, cached so that late joiners get the newest."""
        return f"{self.root}/weights/policy"

    @property
    def weights_latest(self) -> str:
        """Queryable fallback for pulling the newest weights."""
        return f"{self.root}/weights/latest"

    @property
    def levels_sample(self) -> str:
        """Queryable of the curriculum: actors pull batches of levels from it."""
        return f"{self.root}/levels/sample"

    def levels_results(self, actor: str) -> str:
        """Per-level results published by one actor to the curriculum."""
        return f"{self.root}/levels/results/{check_name(actor, 'actor id')}"

    @property
    def levels_results_all(self) -> str:
        """Pattern matching every actor's level results (the curriculum's subscription)."""
        return f"{self.root}/levels/results/*"

    @property
    def curriculum_knobs(self) -> str:
        """Queryable of the curriculum: read or change its live knobs (`impulse curriculum get|set`)."""
        return f"{self.root}/curriculum/knobs"

    @property
    def curriculum_inspect(self) -> str:
        """Queryable of the curriculum: its buffer statistics and levels (`impulse curriculum inspect`)."""
        return f"{self.root}/curriculum/inspect"

    def ctrl(self, role: str, ident: str) -> str:
        """Control messages (pause, resume, shutdown) addressed to one process."""
        return f"{self.root}/ctrl/{check_name(role, 'role')}/{check_name(ident, 'id')}"

    @property
    def ctrl_all(self) -> str:
        """Control messages addressed to every process of the run."""
        return f"{self.root}/ctrl/all"

    def metrics(self, role: str, ident: str) -> str:
        """Metrics published by one process."""
        return f"{self.root}/metrics/{check_name(role, 'role')}/{check_name(ident, 'id')}"

    @property
    def metrics_all(self) -> str:
        """Pattern matching every process's metrics."""
        return f"{self.root}/metrics/**"

    def alive(self, role: str, ident: str) -> str:
        """Liveliness token of one process: present while its session is up."""
        return f"{self.root}/alive/{check_name(role, 'role')}/{check_name(ident, 'id')}"

    def alive_pattern(self, role: str | None = None) -> str:
        """Pattern matching the liveliness tokens of one role, or of every process when `role` is None."""
        if role is None:
            return f"{self.root}/alive/**"
        return f"{self.root}/alive/{check_name(role, 'role')}/*"

    def parse_alive(self, key: str) -> tuple[str, str]:
        """(role, ident) of a liveliness key of this run; ValueError if `key` is not one."""
        prefix = f"{self.root}/alive/"
        rest = key[len(prefix) :] if key.startswith(prefix) else ""
        role, sep, ident = rest.partition("/")
        if not sep or not role or not ident or "/" in ident:
            raise ValueError(f"{key!r} is not a liveliness key of run {self.run!r} ({prefix}<role>/<id>)")
        return role, ident
