"""The bus across machines: a Zenoh router, its TLS and authentication, and who may publish what.

On one machine the processes are peers around a hub (`bus.session`). Across machines every process is a client
of a router (`impulse router`, one per host or one for the run) and all traffic passes through routers, which is
what lets a router enforce access control: a peer-to-peer link would bypass it.

Security material lives in one credentials directory (made for trials by deploy/cluster/security/make-test-certs.sh):

- `ca.pem`: the certificate authority everyone trusts; with it the bus runs over TLS (`tls/HOST:PORT` endpoints);
- `router.pem`, `router.key`: the router's certificate, whose names clients verify;
- `<role>.pem`, `<role>.key`: a process's client certificate, its common name the role (mutual TLS);
- `<role>.password`: a process's password for Zenoh's user/password authentication, the user being the role;
- `users.txt`: the router's `role:password` dictionary;
- `router.password`: what a router presents when it links to another (`router.connect`), the user being `router`.

A host holds only the files of the roles it runs. The roles are `bus.keys.ROLES`: `learner`, `curriculum`,
`actor`, and `operator` for the command-line tools (`impulse curriculum get|set|inspect|inject`, status watchers).

With access control on, the router denies by default and allows each role only its part of the protocol
(`access_rules`): each role publishes only under its own key prefix (`bus.keys`), so only the learner can publish
weights, credits and the learner's status, only the curriculum can answer level and knob queries, only actors can
publish trajectories and level results, and only operators (and actors, for levels) may ask the curriculum;
trajectories reach only the learner. Receivers tell who sent a message by the key it arrived on, which is what the
router guarantees; a frame carries no sender name (docs/multi-host.md, "Threat model").

Routers linked to each other (one per host, `router.connect`) trust each other: a router is recognised by its
certificate (common name `router`; a router sees the certificate of one it connects to but not its user name, so
linked routers with access control need mutual TLS), presents `router.password` where passwords are required, and
may pass on anything, since each router enforces the rules above on the clients connected to it. Guard
`router.key` and `router.password` accordingly.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from impulse.bus.config import RouterConfig, is_loopback
from impulse.bus.keys import (
    ACTOR,
    CURRICULUM,
    EVALUATOR,
    LEARNER,
    OPERATOR,
    PREFIX,
    RECORDER,
    ROLES,
    SCHEMA_MAJOR,
)

log = logging.getLogger("impulse.router")

CA_FILE = "ca.pem"
ROUTER_ROLE = "router"
USERS_FILE = "users.txt"
ALL_MESSAGES = ["put", "delete", "query", "reply", "declare_subscriber", "declare_queryable", "liveliness_token",
                "liveliness_query", "declare_liveliness_subscriber"]
"""Every message kind zenoh's access control names: what one router may pass to another."""


class CredentialsError(ValueError):
    """The credentials directory lacks a file the configuration needs."""


@dataclass(frozen=True)
class Security:
    """What a credentials directory provides, found once (files are read by zenoh itself)."""

    directory: Path
    tls: bool
    passwords: bool

    @staticmethod
    def find(credentials: str) -> Security | None:
        if not credentials:
            return None
        directory = Path(credentials).expanduser()
        if not directory.is_dir():
            raise CredentialsError(f"credentials directory {directory} does not exist")
        return Security(directory, (directory / CA_FILE).is_file(), (directory / USERS_FILE).is_file())

    def file(self, name: str) -> str:
        path = self.directory / name
        if not path.is_file():
            raise CredentialsError(f"{path} is missing from the credentials directory")
        return str(path)


def client_security(credentials: str, role: str) -> dict[str, Any]:
    """Zenoh settings for a client process of `role`: TLS trust (and its certificate when one is there) and its
    user/password when a password file is there. Roles other than ROLES (the launcher, command-line tools) use
    the operator's. Raises CredentialsError when the directory has neither."""
    security = Security.find(credentials)
    if security is None:
        return {}
    role = role if role in ROLES else OPERATOR
    settings: dict[str, Any] = {}
    if security.tls:
        tls: dict[str, Any] = {"root_ca_certificate": security.file(CA_FILE)}
        if (security.directory / f"{role}.pem").is_file():
            tls.update(connect_certificate=security.file(f"{role}.pem"),
                       connect_private_key=security.file(f"{role}.key"), enable_mtls=True)
        settings["transport/link/tls"] = tls
    password = security.directory / f"{role}.password"
    if password.is_file():
        settings["transport/auth/usrpwd"] = {"user": role, "password": password.read_text().strip()}
    if not settings:
        raise CredentialsError(f"credentials directory {security.directory} holds neither {CA_FILE} nor "
                               f"{role}.password")
    return settings


def _allow(rule_id: str, flow: str, messages: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": keys}


def access_rules(by_certificate: bool, by_password: bool) -> dict[str, Any]:
    """Zenoh access control for the router: deny by default, then each role's part of the protocol.

    Each role may publish (put, reply, declare a queryable or a liveliness token) only under its own prefix
    `impulse/*/v2/<role>/**` (`bus.keys`), so a receiver can tell who sent a message from its key. `ingress` rules
    say what a role may send into the router, `egress` what the router may deliver to it: trajectories reach only
    the learner and the recorder (which also hears the levels the actors play), level results only the curriculum,
    the learner's weights, credits and status reach actors (and
    its weights and status the evaluator, whose evaluations reach the learner, and the curriculum service, which
    scores candidate levels with them in batch-scored SFL), and every process may hear status lines. Keys cover
    every run; the advanced publisher's cache for late joiners lives under `learner/weights/policy/@adv/**`,
    which `**` does not match (`@` chunks match only themselves), hence its own keys.
    """
    run = f"{PREFIX}/*/v{SCHEMA_MAJOR}"
    weights_cache = f"{run}/{LEARNER}/weights/policy/@adv/**"
    everything = [f"{PREFIX}/**", weights_cache]

    def own(role: str) -> list[str]:
        return [f"{run}/{role}/**", *([weights_cache] if role == LEARNER else [])]

    listening = ["declare_subscriber", "liveliness_query", "declare_liveliness_subscriber"]
    publishing = ["put", "reply", "declare_queryable", "liveliness_token"]
    rules = [
        _allow("listen", "ingress", listening, everything),
        _allow("hear-declarations", "egress", [*listening, "declare_queryable", "liveliness_token", "reply"],
               everything),
        _allow("hear-statuses", "egress", ["put"], [f"{run}/*/status/*"]),
        *(_allow(f"{role}-publishes", "ingress", publishing, own(role)) for role in ROLES),
        _allow("learner-hears", "egress", ["put", "query"], [f"{run}/{ACTOR}/traj/*", f"{run}/{EVALUATOR}/results/*",
                                                             *own(LEARNER)]),
        _allow("actor-asks", "ingress", ["query"], [f"{run}/{LEARNER}/weights/**", weights_cache,
                                                    f"{run}/{CURRICULUM}/levels/sample"]),
        _allow("actor-hears", "egress", ["put"], [f"{run}/{LEARNER}/**"]),
        _allow("evaluator-asks", "ingress", ["query"], [f"{run}/{LEARNER}/weights/**", weights_cache]),
        _allow("evaluator-hears", "egress", ["put"], [f"{run}/{LEARNER}/**"]),
        _allow("recorder-hears", "egress", ["put"], [f"{run}/{ACTOR}/traj/*", f"{run}/{ACTOR}/played/*",
                                                     f"{run}/{LEARNER}/**"]),
        _allow("curriculum-asks", "ingress", ["query"], [f"{run}/{LEARNER}/weights/**", weights_cache]),
        _allow("curriculum-hears", "egress", ["put", "query"], [f"{run}/{ACTOR}/results/*", *own(CURRICULUM)]),
        _allow("curriculum-hears-learner", "egress", ["put"], [f"{run}/{LEARNER}/**"]),
        _allow("operator-asks", "ingress", ["query"], [f"{run}/{CURRICULUM}/knobs", f"{run}/{CURRICULUM}/inspect",
                                                       f"{run}/{CURRICULUM}/inject"]),
        _allow("router-passes-in", "ingress", ALL_MESSAGES, everything),
        _allow("router-passes-out", "egress", ALL_MESSAGES, everything),
    ]
    own_rules = {
        LEARNER: ["learner-hears"],
        CURRICULUM: ["curriculum-asks", "curriculum-hears", "curriculum-hears-learner"],
        ACTOR: ["actor-asks", "actor-hears"],
        EVALUATOR: ["evaluator-asks", "evaluator-hears"],
        RECORDER: ["recorder-hears"],
        OPERATOR: ["operator-asks"],
    }
    subjects, policies = [], []
    for role in ROLES:
        subject: dict[str, Any] = {"id": role}
        if by_certificate:
            subject["cert_common_names"] = [role]
        if by_password:
            subject["usernames"] = [role]
        subjects.append(subject)
        policies.append({"id": role, "subjects": [role], "rules": ["listen", "hear-declarations", "hear-statuses",
                                                                   f"{role}-publishes", *own_rules[role]]})
    if by_certificate:
        # By certificate alone: a router sees the certificate of a router it connects to, but not its user name.
        subjects.append({"id": ROUTER_ROLE, "cert_common_names": [ROUTER_ROLE]})
        policies.append({"id": ROUTER_ROLE, "subjects": [ROUTER_ROLE], "rules": ["router-passes-in",
                                                                                 "router-passes-out"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_zenoh_config(config: RouterConfig, lease_ms: int = 3000) -> zenoh.Config:
    """The zenoh configuration of a router: its endpoints, TLS, user/password dictionary and access control.
    Raises CredentialsError for missing files or access control without any way to tell roles apart."""
    settings: dict[str, Any] = {
        "mode": "router",
        "scouting/multicast/enabled": False,
        "timestamping/enabled": True,
        "listen/endpoints": list(config.listen),
        "connect/endpoints": list(config.connect),
        "connect/timeout_ms": -1,
        "connect/exit_on_failure": False,
        "transport/link/tx/lease": lease_ms,
    }
    security = Security.find(config.credentials)
    by_certificate = by_password = False
    if security is not None:
        if security.tls:
            settings["transport/link/tls"] = {
                "root_ca_certificate": security.file(CA_FILE),
                "listen_certificate": security.file(f"{ROUTER_ROLE}.pem"),
                "listen_private_key": security.file(f"{ROUTER_ROLE}.key"),
                "connect_certificate": security.file(f"{ROUTER_ROLE}.pem"),
                "connect_private_key": security.file(f"{ROUTER_ROLE}.key"),
                "enable_mtls": config.mutual_tls,
            }
            by_certificate = config.mutual_tls
        if security.passwords:
            usrpwd = {"dictionary_file": security.file(USERS_FILE)}
            if config.connect or (security.directory / f"{ROUTER_ROLE}.password").is_file():
                password = Path(security.file(f"{ROUTER_ROLE}.password")).read_text().strip()
                usrpwd.update(user=ROUTER_ROLE, password=password)
            settings["transport/auth/usrpwd"] = usrpwd
            by_password = True
    if config.access_control and security is not None:
        if not (by_certificate or by_password):
            raise CredentialsError("router.access_control needs a way to tell roles apart: mutual TLS (ca.pem, "
                                   "router.pem/.key) or passwords (users.txt) in the credentials directory")
        if config.connect and not by_certificate:
            raise CredentialsError("router.connect with access control needs mutual TLS (ca.pem, router.pem/.key "
                                   "and router.mutual_tls): linked routers recognise each other by certificate")
        settings["access_control"] = access_rules(by_certificate, by_password)
    conf = zenoh.Config()
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def open_listeners_warning(config: RouterConfig) -> str | None:
    """A warning when the router listens beyond loopback without authentication, else None."""
    exposed = [e for e in config.listen if not is_loopback(e)]
    if not exposed:
        return None
    security = Security.find(config.credentials)
    if security is not None and (security.passwords or (security.tls and config.mutual_tls)):
        return None
    return (f"the router listens on {', '.join(exposed)} without authentication: anyone who can reach it can read "
            "trajectories and publish weights; set router.credentials (deploy/cluster/security/make-test-certs.sh "
            "makes trial ones) or listen on loopback only")


def run_router(config: RouterConfig, stop: threading.Event | Callable[[], bool], poll_s: float = 0.1,
               lease_ms: int = 3000) -> None:
    """Keep a router open until `stop` is set (an Event) or returns True (a callable)."""
    stopped = stop.is_set if isinstance(stop, threading.Event) else stop
    session = zenoh.open(router_zenoh_config(config, lease_ms))
    try:
        log.info("router %s listening on %s%s", session.info.zid(), ", ".join(config.listen),
                 f", linked to {', '.join(config.connect)}" if config.connect else "")
        while not stopped():
            time.sleep(poll_s)
    finally:
        session.close()
