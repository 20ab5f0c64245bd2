"""The router's configuration refuses what cannot work, naming the missing piece, rather than starting a router
whose links or clients would be silently denied; its access control gives each role what the role declares."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from impulse.bus.config import RouterConfig
from impulse.bus.roles import FOLLOWS_WEIGHTS, LEARNER_BROADCASTS, PROTOCOL_ROLES, Role
from impulse.bus.router import CredentialsError, access_rules, router_zenoh_config
from tests.support.credentials import make_credentials


@pytest.fixture(scope="module")
def credentials(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_credentials(tmp_path_factory.mktemp("credentials"))


def copy_without(source: Path, target: Path, *names: str) -> Path:
    shutil.copytree(source, target)
    for name in names:
        (target / name).unlink()
    return target


def test_make_test_certs_leaves_no_authority_key_and_a_private_directory(credentials: Path) -> None:
    assert not (credentials / "ca.key").exists()
    assert credentials.stat().st_mode & 0o777 == 0o700
    users = dict(line.split(":") for line in (credentials / "users.txt").read_text().split())
    assert set(users) == {"router", "learner", "curriculum", "actor", "evaluator", "recorder", "operator"}  # the
    # roles `impulse router --roles` lists
    assert users["router"] == (credentials / "router.password").read_text().strip()


def test_linked_routers_are_recognised_by_certificate_only() -> None:
    rules = access_rules(PROTOCOL_ROLES, by_certificate=True, by_password=True)
    assert {"id": "router", "cert_common_names": ["router"]} in rules["subjects"]
    without_tls = access_rules(PROTOCOL_ROLES, by_certificate=False, by_password=True)
    assert "router" not in {subject["id"] for subject in without_tls["subjects"]}


def test_router_link_with_access_control_needs_mutual_tls(credentials: Path, tmp_path: Path) -> None:
    linked = dict(listen=("tcp/127.0.0.1:7447",), connect=("tcp/127.0.0.1:7448",))
    router_zenoh_config(RouterConfig(**linked, credentials=str(credentials)), PROTOCOL_ROLES)  # mutual TLS: fine
    with pytest.raises(CredentialsError, match="mutual TLS"):
        router_zenoh_config(RouterConfig(**linked, credentials=str(credentials), mutual_tls=False), PROTOCOL_ROLES)
    passwords_only = copy_without(credentials, tmp_path / "passwords", "ca.pem")
    with pytest.raises(CredentialsError, match="mutual TLS"):
        router_zenoh_config(RouterConfig(**linked, credentials=str(passwords_only)), PROTOCOL_ROLES)
    no_router_password = copy_without(credentials, tmp_path / "no-password", "router.password")
    with pytest.raises(CredentialsError, match="router.password"):
        router_zenoh_config(RouterConfig(**linked, credentials=str(no_router_password)), PROTOCOL_ROLES)
    router_zenoh_config(RouterConfig(listen=linked["listen"], credentials=str(no_router_password)),
                        PROTOCOL_ROLES)  # unlinked


def policy_rules(rules: dict, role: str) -> dict[str, dict]:
    """The rules of `role`'s policy, by id."""
    (policy,) = [p for p in rules["policies"] if p["id"] == role]
    by_id = {rule["id"]: rule for rule in rules["rules"]}
    return {rule_id: by_id[rule_id] for rule_id in policy["rules"]}


def test_a_role_gets_exactly_what_it_declares() -> None:
    watcher = Role("watcher", asks=FOLLOWS_WEIGHTS, hears=(*LEARNER_BROADCASTS, "actor/results/*"))
    rules = access_rules((*PROTOCOL_ROLES, watcher), by_certificate=True, by_password=False)
    assert {"id": "watcher", "cert_common_names": ["watcher"]} in rules["subjects"]
    granted = policy_rules(rules, "watcher")
    assert set(granted) == {"listen", "hear-declarations", "hear-statuses", "watcher-publishes", "watcher-asks",
                            "watcher-hears"}
    run = "impulse/*/v2"
    assert granted["watcher-publishes"]["key_exprs"] == [f"{run}/watcher/**"]
    assert granted["watcher-publishes"]["flows"] == ["ingress"]
    assert granted["watcher-asks"]["key_exprs"] == [f"{run}/learner/weights/**",
                                                    f"{run}/learner/weights/policy/@adv/**"]
    assert granted["watcher-asks"]["messages"] == ["query"]
    assert granted["watcher-hears"] == {"id": "watcher-hears", "permission": "allow", "flows": ["egress"],
                                        "messages": ["put"], "key_exprs": [f"{run}/learner/**",
                                                                           f"{run}/actor/results/*"]}
    # Declaring it changes no other role's policy.
    without = access_rules(PROTOCOL_ROLES, by_certificate=True, by_password=False)
    for role in PROTOCOL_ROLES:
        assert policy_rules(rules, role.name) == policy_rules(without, role.name)
    # Only roles that answer queries hear them; only the learner's prefix covers the weights cache.
    assert set(policy_rules(rules, "learner")) >= {"learner-answers", "learner-hears"}
    assert f"{run}/learner/weights/policy/@adv/**" in policy_rules(rules, "learner")["learner-publishes"]["key_exprs"]
    assert "actor-answers" not in policy_rules(rules, "actor")


def test_roles_must_be_distinct_and_not_named_like_a_router() -> None:
    with pytest.raises(ValueError, match="distinct"):
        access_rules((*PROTOCOL_ROLES, Role("actor")), by_certificate=False, by_password=True)
    with pytest.raises(ValueError, match="router"):
        access_rules((*PROTOCOL_ROLES, Role("router")), by_certificate=False, by_password=True)
    with pytest.raises(ValueError, match="not allowed in a key chunk"):
        Role("two/chunks")
