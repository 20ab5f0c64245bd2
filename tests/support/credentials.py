"""Trial credentials for tests of routers with TLS, passwords and access control: what
deploy/cluster/security/make-test-certs.sh writes, for the roles this checkout's `impulse router --roles` lists."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.paths import REPO

CERT_SCRIPT = REPO / "deploy" / "cluster" / "security" / "make-test-certs.sh"


def make_credentials(directory: Path, *router_hosts: str) -> Path:
    """Run the script into `directory` (router reached as localhost, 127.0.0.1 and `router_hosts`); skip the test
    where openssl is missing."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is needed to make test certificates")
    impulse = f"{shlex.quote(sys.executable)} -m impulse.deploy.cli"
    made = subprocess.run(["bash", str(CERT_SCRIPT), str(directory), *router_hosts], capture_output=True, text=True,
                          env={**os.environ, "IMPULSE": impulse}, cwd=REPO)
    assert made.returncode == 0, made.stderr
    return directory
