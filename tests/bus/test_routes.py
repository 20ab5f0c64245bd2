"""The route table (`bus.routes`): every message family can reach someone, and the keys are the table's.

That every route's decoder is fuzzed is tests/bus/test_fuzz_decoders.py's `test_every_route_has_a_fuzzed_decoder`.
"""

from __future__ import annotations

import pytest
import zenoh

from impulse.bus.keys import Keys
from impulse.bus.roles import PROTOCOL_ROLES
from impulse.bus.routes import ANY_ROLE, ROUTE, ROUTES, patterns
from impulse.deploy.commands import run_roles


def covered(pattern: str, allowed: tuple[str, ...]) -> bool:
    return any(zenoh.KeyExpr(rule).includes(zenoh.KeyExpr(pattern)) for rule in allowed)


@pytest.mark.parametrize("route", [r for r in ROUTES if r.sender != ANY_ROLE], ids=lambda r: r.name)
def test_every_route_is_heard_or_asked_by_a_role(route) -> None:
    """A route nobody may hear (or ask, for a queryable) would be refused by every secured router: dead on arrival.
    Status lines and liveliness are every role's, and every role hears them (`bus.router.access_rules`)."""
    roles = {role.name: role for role in (*PROTOCOL_ROLES, *run_roles())}
    reached = [name for name, role in roles.items()
               if covered(route.pattern, role.asks if route.queried else role.hears)]
    assert reached, f"no role may {'ask' if route.queried else 'hear'} {route.pattern}"
    assert route.sender in roles, f"{route.name} is published by {route.sender!r}, which is no role"


def test_keys_are_built_from_the_routes() -> None:
    keys = Keys("r")
    root = keys.root
    built = {"weights": keys.weights_policy, "weights_latest": keys.weights_latest, "credit": keys.credit("a0"),
             "levels_sample": keys.levels_sample, "curriculum_knobs": keys.curriculum_knobs,
             "curriculum_inspect": keys.curriculum_inspect, "curriculum_inject": keys.curriculum_inject,
             "traj": keys.traj("a0"), "levels_results": keys.levels_results("a0"),
             "levels_played": keys.levels_played("a0"), "evaluations": keys.evaluation("e0"),
             "status": keys.status("actor", "a0"), "alive": keys.alive("learner", "l0")}
    assert set(built) == set(ROUTE), "a route without a key method, or the reverse"
    for name, key in built.items():
        pattern = ROUTE[name].pattern.replace(ANY_ROLE, "*", 1) if ROUTE[name].sender == ANY_ROLE else \
            ROUTE[name].pattern
        assert zenoh.KeyExpr(f"{root}/{pattern}").includes(zenoh.KeyExpr(key)), (name, key)
    assert keys.traj_all == f"{root}/{ROUTE['traj'].pattern}"


def test_an_unknown_route_name_is_refused_with_the_routes_listed() -> None:
    with pytest.raises(KeyError, match="no route named trajectories; routes: weights, "):
        patterns("traj", "trajectories")
    with pytest.raises(ValueError, match="one key per sender"):
        Keys("r").key("traj")
    with pytest.raises(ValueError, match="published by every role"):
        Keys("r").key("status", "a0")
