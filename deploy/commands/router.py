"""`impulse router`: the Zenoh router of a multi-host run (docs/multi-host.md).

It reads the `[router]` section of a run config (listen endpoints, other routers, credentials, access control),
warns when it listens beyond loopback without authentication, and runs until SIGINT or SIGTERM. Learner,
curriculum and actors on any host join with `--connect ENDPOINT` (or `bus.connect`), as clients of it.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys

from impulse.bus.router import CredentialsError, open_listeners_warning, run_router
from impulse.deploy.commands import run_roles
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_FAILED, EXIT_USAGE
from impulse.deploy.runtime.runloop import StopFlag

log = logging.getLogger("impulse.router")


def run_router_command(args: argparse.Namespace, config: RunConfig) -> int:
    roles = run_roles()
    if args.roles:
        print("\n".join(role.name for role in roles))
        return 0
    router = config.router
    if args.listen:
        try:
            router = dataclasses.replace(router, listen=tuple(args.listen))
        except ValueError as err:
            print(f"impulse router: --listen: {err}", file=sys.stderr)
            return EXIT_USAGE
    warning = open_listeners_warning(router)
    if warning:
        log.warning(warning)
    with StopFlag("stopping the router") as stop:
        try:
            run_router(router, roles, lambda: stop.stop, lease_ms=config.bus.lease_ms)
        except CredentialsError as err:
            print(f"impulse router: {err}", file=sys.stderr)
            return EXIT_USAGE
        except Exception as err:  # zenoh reports a taken port or a bad certificate as ZError
            print(f"impulse router: could not start: {err}", file=sys.stderr)
            return EXIT_FAILED
    log.info("router stopped")
    return 0
