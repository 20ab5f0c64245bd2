"""Every message family of a run, once: the route table the keys, the roles' access and the fuzz tests read.

A route is one family of messages: the role whose prefix it is published under (only that role may publish there,
where a router enforces it), the key chunks after that prefix, whether one more chunk names the sending process
(an actor's id: per sender) or not (shared), whether it is put (heard by subscribers) or answered (a queryable
that others ask), the frame kind it carries and the function that decodes it. `bus.keys.Keys` builds every key
from this table, `bus.roles` states what each role hears and asks by route name, `bus.router.access_rules` turns
those into Zenoh's rules, and tests/bus/test_routes.py checks that every route has a fuzzed decoder and that
some role may hear or ask it.

A new message family is one entry here (and its codec module); who may hear or ask it is one name in a role.
Status lines and liveliness tokens, which every process publishes under its own role's prefix, are the two
entries whose sender is any role (`ANY_ROLE`).
"""

from __future__ import annotations

from dataclasses import dataclass

from impulse.bus.codec import Kind

LEARNER = "learner"
CURRICULUM = "curriculum"
ACTOR = "actor"
EVALUATOR = "evaluator"
RECORDER = "recorder"
OPERATOR = "operator"
"""The `<role>` chunks of the roles that publish the routes below; the operator is any command-line tool, the
launcher or a watcher. What each may ask and hear is `bus.roles` (and, for roles added beside the protocol's,
their command modules); across machines each role has credentials of its own (`bus.router`)."""

ANY_ROLE = "*"
"""The sender of a route every process publishes under its own role's prefix (status lines, liveliness)."""

STATUS = "status"
ALIVE = "alive"


@dataclass(frozen=True)
class Route:
    """One message family: where it is published, by whom, what it carries."""

    name: str
    """What the rest of the code calls it (`Keys.key(name, ...)`, a role's `hears` and `asks`)."""
    sender: str
    """The role whose prefix it is published under, or `ANY_ROLE`."""
    topic: tuple[str, ...]
    """The key chunks after the sender's prefix."""
    kind: Kind | None
    """The frame kind it carries (None: a liveliness token, which carries nothing)."""
    decoder: str | None
    """The function that reads its frames, as `module.function` under the `impulse` package (None: nothing to
    decode)."""
    per_sender: bool = False
    """Whether one more chunk names the sending process (`<actor>`, `<id>`): each sender publishes its own key,
    and a receiver subscribes to all of them with `*`. That chunk tells senders apart; it does not authenticate
    one (all processes of a role share its credential)."""
    queried: bool = False
    """Whether it is a queryable that others ask (a role's `asks`) rather than puts that others hear (`hears`)."""
    summary: str = ""

    @property
    def pattern(self) -> str:
        """Its keys under a run's root, with `*` for the sender's chunk (and for the role, for `ANY_ROLE`)."""
        return "/".join((self.sender, *self.topic, *(("*",) if self.per_sender else ())))


ROUTES: tuple[Route, ...] = (
    Route("weights", LEARNER, ("weights", "policy"), Kind.WEIGHTS, "bus.weights.decode_weights",
          summary="the policy's weights, broadcast (cached for late joiners under .../@adv/pub/...)"),
    Route("weights_latest", LEARNER, ("weights", "latest"), Kind.WEIGHTS, "bus.weights.decode_weights", queried=True,
          summary="the newest weights, for a follower that missed the broadcast"),
    Route("credit", LEARNER, ("credit",), Kind.CREDIT, "bus.credits.decode_credit", per_sender=True,
          summary="acknowledgements (credits) for one actor, keyed by the actor's id"),
    Route("levels_sample", CURRICULUM, ("levels", "sample"), Kind.LEVELS, "bus.levels.decode_level_batch",
          queried=True, summary="a batch of levels to play next"),
    Route("curriculum_knobs", CURRICULUM, ("knobs",), Kind.CONTROL, "bus.control.decode_report", queried=True,
          summary="read or change the live knobs (`impulse curriculum get|set`)"),
    Route("curriculum_inspect", CURRICULUM, ("inspect",), Kind.CONTROL, "bus.control.decode_report", queried=True,
          summary="the buffer's statistics and levels (`impulse curriculum inspect`)"),
    Route("curriculum_inject", CURRICULUM, ("inject",), Kind.CONTROL, "bus.control.decode_report", queried=True,
          summary="put a level a person sends into the buffer (`impulse curriculum inject`, the studio)"),
    Route("traj", ACTOR, ("traj",), Kind.TRAJECTORY, "bus.trajectories.decode_trajectory", per_sender=True,
          summary="trajectory batches"),
    Route("levels_results", ACTOR, ("results",), Kind.LEVEL_RESULTS, "bus.levels.decode_level_results",
          per_sender=True, summary="per-level results of the episodes played"),
    Route("levels_played", ACTOR, ("played",), Kind.LEVELS, "bus.levels.decode_level_batch", per_sender=True,
          summary="the level batch an actor plays next (published only while a recorder listens)"),
    Route("evaluations", EVALUATOR, ("results",), Kind.EVALUATION, "bus.evaluations.decode_evaluation",
          per_sender=True, summary="scores of the learner's policies on level sets"),
    Route("status", ANY_ROLE, (STATUS,), Kind.METRICS, "bus.status.read_status", per_sender=True,
          summary="status lines, every process's under its own role"),
    Route("alive", ANY_ROLE, (ALIVE,), None, None, per_sender=True,
          summary="liveliness tokens, every process's under its own role (the learner's second one, "
                  "instance-<nonce>, names its start)"),
)

ROUTE: dict[str, Route] = {route.name: route for route in ROUTES}
"""Every route by its name."""


def patterns(*names: str) -> tuple[str, ...]:
    """The key patterns (under a run's root) of the routes `names`, for a role's `hears` or `asks`; KeyError
    naming an unknown route."""
    unknown = [name for name in names if name not in ROUTE]
    if unknown:
        raise KeyError(f"no route named {', '.join(unknown)}; routes: {', '.join(ROUTE)}")
    return tuple(ROUTE[name].pattern for name in names)
