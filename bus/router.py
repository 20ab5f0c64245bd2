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

A host holds only the files of the roles it runs. The roles are `bus.roles.Role`s: the protocol's `learner`,
`curriculum`, `actor`, and `operator` for the command-line tools (`impulse curriculum get|set|inspect|inject`,
status watchers), and the roles added beside them (`impulse router` lists them all with `--roles`).

With access control on, the router denies by default and allows each role only its part of the protocol
(`access_rules`): each role publishes only under its own key prefix (`bus.keys`), so only the learner can publish
weights, credits and the learner's status, only the curriculum can answer level and knob queries, only actors can
publish trajectories and level results, and only operators (and actors, for levels) may ask the curriculum;
trajectories reach only the learner and the recorder. Receivers tell who sent a message by the key it arrived on,
which is what the router guarantees; a frame carries no sender name (docs/multi-host.md, "Threat model").

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from impulse.bus.config import RouterConfig, is_loopback
from impulse.bus.keys import LEARNER, PREFIX, SCHEMA_MAJOR
from impulse.bus.roles import WEIGHTS_CACHE, Role

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
    user/password when a password file is there. Raises CredentialsError when the directory has neither."""
    security = Security.find(credentials)
    if security is None:
        return {}
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


def access_rules(roles: Sequence[Role], by_certificate: bool, by_password: bool) -> dict[str, Any]:
    """Zenoh access control for the router: deny by default, then each role's part of the protocol.

    Each role may publish (put, reply, declare a queryable or a liveliness token) only under its own prefix
    `impulse/*/v2/<role>/**` (`bus.keys`), so a receiver can tell who sent a message from its key. Beyond that a
    role may query what its `Role.asks` names (ingress), and the router delivers to it the puts its `Role.hears`
    names, every status line, and, for a role that `answers`, the puts and queries under its own prefix (egress).
    With the protocol's roles (`bus.roles`) that means: trajectories reach only the learner (and a recorder, if
    one is declared), level results only the curriculum, the learner's weights, credits and status its
    followers, and only operators may ask the curriculum's knobs. Keys cover every run; the learner's prefix
    also covers the weights cache for late joiners (`bus.roles.WEIGHTS_CACHE`). Raises ValueError when two roles
    share a name or one is named like a router.
    """
    names = [role.name for role in roles]
    if len(set(names)) != len(names) or ROUTER_ROLE in names:
        raise ValueError(f"roles must have distinct names other than {ROUTER_ROLE!r}, got {', '.join(names)}")
    run = f"{PREFIX}/*/v{SCHEMA_MAJOR}"
    everything = [f"{PREFIX}/**", f"{run}/{WEIGHTS_CACHE}"]

    def under_run(patterns: Sequence[str]) -> list[str]:
        return [f"{run}/{pattern}" for pattern in patterns]

    def own(role: Role) -> list[str]:
        return under_run([f"{role.name}/**", *([WEIGHTS_CACHE] if role.name == LEARNER else [])])

    listening = ["declare_subscriber", "liveliness_query", "declare_liveliness_subscriber"]
    publishing = ["put", "reply", "declare_queryable", "liveliness_token"]
    rules = [
        _allow("listen", "ingress", listening, everything),
        _allow("hear-declarations", "egress", [*listening, "declare_queryable", "liveliness_token", "reply"],
               everything),
        _allow("hear-statuses", "egress", ["put"], [f"{run}/*/status/*"]),
        _allow("router-passes-in", "ingress", ALL_MESSAGES, everything),
        _allow("router-passes-out", "egress", ALL_MESSAGES, everything),
    ]
    subjects, policies = [], []
    for role in roles:
        own_rules = [_allow(f"{role.name}-publishes", "ingress", publishing, own(role))]
        if role.asks:
            own_rules.append(_allow(f"{role.name}-asks", "ingress", ["query"], under_run(role.asks)))
        if role.hears:
            own_rules.append(_allow(f"{role.name}-hears", "egress", ["put"], under_run(role.hears)))
        if role.answers:
            own_rules.append(_allow(f"{role.name}-answers", "egress", ["put", "query"], own(role)))
        rules.extend(own_rules)
        subject: dict[str, Any] = {"id": role.name}
        if by_certificate:
            subject["cert_common_names"] = [role.name]
        if by_password:
            subject["usernames"] = [role.name]
        subjects.append(subject)
        policies.append({"id": role.name, "subjects": [role.name],
                         "rules": ["listen", "hear-declarations", "hear-statuses", *(r["id"] for r in own_rules)]})
    if by_certificate:
        # By certificate alone: a router sees the certificate of a router it connects to, but not its user name.
        subjects.append({"id": ROUTER_ROLE, "cert_common_names": [ROUTER_ROLE]})
        policies.append({"id": ROUTER_ROLE, "subjects": [ROUTER_ROLE], "rules": ["router-passes-in",
                                                                                 "router-passes-out"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_zenoh_config(config: RouterConfig, roles: Sequence[Role], lease_ms: int = 3000) -> zenoh.Config:
    """The zenoh configuration of a router: its endpoints, TLS, user/password dictionary and access control for
    `roles`. Raises CredentialsError for missing files or access control without any way to tell roles apart."""
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
        settings["access_control"] = access_rules(roles, by_certificate, by_password)
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


def run_router(config: RouterConfig, roles: Sequence[Role], stop: threading.Event | Callable[[], bool],
               poll_s: float = 0.1, lease_ms: int = 3000) -> None:
    """Keep a router for a run of `roles` open until `stop` is set (an Event) or returns True (a callable)."""
    stopped = stop.is_set if isinstance(stop, threading.Event) else stop
    session = zenoh.open(router_zenoh_config(config, roles, lease_ms))
    try:
        log.info("router %s listening on %s%s", session.info.zid(), ", ".join(config.listen),
                 f", linked to {', '.join(config.connect)}" if config.connect else "")
        while not stopped():
            time.sleep(poll_s)
    finally:
        session.close()
