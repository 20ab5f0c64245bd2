"""`impulse studio`: serve Impulse Studio (`studio.app`), the browser app to browse, edit and play levels and watch
an agent play them.

Bound to 127.0.0.1 by default. Every request must carry an access token: a random one made at each start, or
`--token T` (required when binding any other address, which makes the studio reachable from the network); the
printed address has it. Requests naming a host other than the studio's own names (`localhost`, its loopback and
bound addresses, `--allow-host` names) are refused, against DNS rebinding (`studio.security`). Starlette and uvicorn
are imported when the command runs, never with the CLI. The studio cannot import `deploy`, so watching an agent
gets its checkpoint loader from here: the run's config.toml resolved as `impulse eval` resolves it, and the policy
restored by `learner.run.restore_policy`. Exit status 2 for usage errors (a token missing or malformed, a port in
use), with one line saying what to do.
"""

from __future__ import annotations

import argparse
import re
import socket
import sys
from pathlib import Path
from typing import Any

from impulse.deploy.config import ConfigError, resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.compile_cache import enable_compile_cache
from impulse.deploy.runtime.exit_codes import EXIT_USAGE
from impulse.deploy.runtime.pilots import load_pilot
from impulse.deploy.runtime.run_dirs import run_dir_of
from impulse.engine.env.spec import env_from_config
from impulse.studio.console import CurriculumLink
from impulse.studio.security import host_name, is_loopback, new_token, studio_address

TOKEN_PATTERN = re.compile(r"[A-Za-z0-9._~-]{8,200}")


def _problem(args: argparse.Namespace) -> str | None:
    if not 0 < args.port < 65536:
        return f"--port must be 1 to 65535, got {args.port}"
    if args.token is not None and not TOKEN_PATTERN.fullmatch(args.token):
        return "--token must be 8 to 200 letters, digits or the characters . _ ~ -"
    if not is_loopback(args.host) and args.token is None:
        return (f"--host {args.host} makes the studio reachable from other machines: give --token T as well (every "
                "request must then carry it), or leave --host at 127.0.0.1")
    for name in args.allow_host:
        if host_name(name) is None:
            return f"--allow-host {name!r}: not a host name or address (letters, digits, '-', '_' and '.')"
    if args.run is not None and not args.run.exists():
        return f"--run {args.run}: no such directory"
    return None


def _port_free(host: str, port: int) -> str | None:
    """None if `host:port` can be listened on, else why not."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as err:
            return f"cannot listen on {host}:{port}: {err.strerror or err}"
    return None


def _offered(args: argparse.Namespace) -> list[str]:
    """Checkpoints the Play page lists: --run, then ./pretrained/* run directories."""
    offered = [str(args.run)] if args.run is not None else []
    pretrained = Path("pretrained")
    if pretrained.is_dir():
        offered += [str(folder) for folder in sorted(pretrained.iterdir()) if (folder / "config.toml").is_file()]
    return offered


def _curriculum_of(run: Path | None) -> Any:
    """A `studio.console.CurriculumLink` to `--run`'s curriculum service when the run trains with one (the
    Curriculum page, and levels sent into its buffer), else None."""
    if run is None:
        return None

    try:
        config = resolve_config(RunConfig, run_dir_of(run) / "config.toml", [])
    except (FileNotFoundError, ConfigError):
        return None
    if not config.uses_curriculum_service:
        return None
    spec, env_params = env_from_config(config.env)
    return CurriculumLink(config.bus, config.name, spec, env_params)


def run(args: argparse.Namespace, _config: object = None) -> int:
    problem = _problem(args) or _port_free(args.host, args.port)
    if problem:
        print(f"impulse studio: {problem}", file=sys.stderr)
        return EXIT_USAGE
    try:
        import uvicorn

        from impulse.studio.app import UVICORN_SETTINGS, make_app
    except ImportError as err:
        print(f"impulse studio: {err.name or err} is not installed: pip install -e . (or starlette and "
              "'uvicorn[standard]')", file=sys.stderr)
        return EXIT_USAGE

    enable_compile_cache()
    token = args.token or new_token()
    app = make_app(args.levels_dir, tuple(args.levels), token=token, host=args.host,
                   allow_hosts=tuple(args.allow_host), load_pilot=load_pilot, agents=_offered(args),
                   curriculum=_curriculum_of(args.run))
    address = studio_address(args.host, args.port, token)
    print(f"Impulse Studio: open {address}  (levels are saved in {args.levels_dir}; Ctrl-C stops)", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_config=None, log_level="warning", **UVICORN_SETTINGS)
    return 0
