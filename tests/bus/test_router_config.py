"""The router's configuration refuses what cannot work, naming the missing piece, rather than starting a router
whose links or clients would be silently denied."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
from impulse.bus.config import RouterConfig
from impulse.bus.router import CredentialsError, access_rules, router_zenoh_config

from tests.support.paths import REPO

CERT_SCRIPT = REPO / "deploy" / "cluster" / "security" / "make-test-certs.sh"


@pytest.fixture(scope="module")
def credentials(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make test certificates")
    directory = tmp_path_factory.mktemp("credentials")
    subprocess.run(["bash", str(CERT_SCRIPT), str(directory)], check=True,
                   capture_output=True)
    return directory


def copy_without(source: Path, target: Path, *names: str) -> Path:
    shutil.copytree(source, target)
    for name in names:
        (target / name).unlink()
    return target


def test_make_test_certs_leaves_no_authority_key_and_a_private_directory(credentials: Path) -> None:
    assert not (credentials / "ca.key").exists()
    assert credentials.stat().st_mode & 0o777 == 0o700
    users = dict(line.split(":") for line in (credentials / "users.txt").read_text().split())
    assert set(users) == {"router", "learner", "curriculum", "actor", "evaluator", "recorder", "operator"}
    assert users["router"] == (credentials / "router.password").read_text().strip()


def test_linked_routers_are_recognised_by_certificate_only() -> None:
    rules = access_rules(by_certificate=True, by_password=True)
    assert {"id": "router", "cert_common_names": ["router"]} in rules["subjects"]
    without_tls = access_rules(by_certificate=False, by_password=True)
    assert "router" not in {subject["id"] for subject in without_tls["subjects"]}


def test_router_link_with_access_control_needs_mutual_tls(credentials: Path, tmp_path: Path) -> None:
    linked = dict(listen=("tcp/127.0.0.1:7447",), connect=("tcp/127.0.0.1:7448",))
    router_zenoh_config(RouterConfig(**linked, credentials=str(credentials)))  # mutual TLS: fine
    with pytest.raises(CredentialsError, match="mutual TLS"):
        router_zenoh_config(RouterConfig(**linked, credentials=str(credentials), mutual_tls=False))
    passwords_only = copy_without(credentials, tmp_path / "passwords", "ca.pem")
    with pytest.raises(CredentialsError, match="mutual TLS"):
        router_zenoh_config(RouterConfig(**linked, credentials=str(passwords_only)))
    no_router_password = copy_without(credentials, tmp_path / "no-password", "router.password")
    with pytest.raises(CredentialsError, match="router.password"):
        router_zenoh_config(RouterConfig(**linked, credentials=str(no_router_password)))
    router_zenoh_config(RouterConfig(listen=linked["listen"], credentials=str(no_router_password)))  # unlinked
