"""The viewer side of `impulse view`: which Rerun processes to start so a run's processes have a server to stream
to and a person has something to look at.

- With a display (DISPLAY or WAYLAND_DISPLAY set): the native viewer, which hosts the gRPC server itself on the
  port of `monitor.url`, with its memory limit (it forgets the oldest data beyond it).
- Without one (a headless or remote machine): `rerun --serve-web`, the gRPC server plus the web viewer over
  HTTP; `web_viewer_address` is the address to open (through an SSH tunnel of both ports when remote).
- `--record FILE` adds a headless recorder: a Rerun process connected to the server that appends everything it
  receives to an .rrd file (the whole run, for `rerun FILE` later).
- `--headless --record FILE` (what `impulse launch --record FILE` starts without `--view`): no viewer at all, one
  Rerun process that is the gRPC server and writes everything it receives to the .rrd file.

The server keeps at most its memory limit for late viewers, dropping the oldest first; the native and web viewers
keep theirs. That is the retention of a live run: the last `server_memory_limit` of data, and the .rrd file when
recording. Both bind to 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from impulse.monitor.stream import server_address


def rerun_binary() -> str:
    """The Rerun executable itself. rerun-sdk installs it inside the `rerun_cli` package; the `rerun` console
    script beside Python only wraps it in a Python process that does not pass signals on, so stopping the wrapper
    would leave the server running. RERUN_CLI_PATH overrides it, as it does for that script."""
    if os.environ.get("RERUN_CLI_PATH"):
        return os.environ["RERUN_CLI_PATH"]
    try:
        import rerun_cli
    except ImportError:
        rerun_cli = None
    if rerun_cli is not None:
        inside = Path(rerun_cli.__file__).parent / "rerun"
        if inside.is_file():
            return str(inside)
    found = shutil.which("rerun")
    if found is None:
        raise FileNotFoundError("the Rerun viewer (the `rerun` command of the rerun-sdk package) is not installed")
    return found


def has_display() -> bool:
    """Whether a native window can open here."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


@dataclass(frozen=True)
class ViewerPlan:
    """The processes `impulse view` starts and what it tells the user."""

    commands: tuple[tuple[str, ...], ...]
    native: bool
    address: str
    """What to open: the web viewer's address, or the gRPC url the native viewer (or the headless recorder)
    serves."""
    headless: bool = False
    """No viewer: the server only records (`address` is then the gRPC url)."""


def web_viewer_address(url: str, web_port: int, host: str | None = None) -> str:
    """The web viewer's address with the run's gRPC url filled in (the form the Rerun web viewer reads)."""
    grpc_host, _ = server_address(url)
    shown = host or grpc_host
    return f"http://{shown}:{web_port}/?url={quote(url.replace(grpc_host, shown, 1), safe='')}"


def viewer_plan(url: str, *, web: bool | None = None, web_port: int = 9090, bind: str = "127.0.0.1",
                server_memory_limit: str = "1GiB", viewer_memory_limit: str = "2GiB",
                record: Path | None = None, headless: bool = False) -> ViewerPlan:
    """The Rerun commands for a run streaming to `url`: native viewer or web viewer (`web`=None: web exactly when
    there is no display), plus a recorder when `record` is given; `headless`: no viewer, only a server that
    records to `record` (which it then needs)."""
    _, port = server_address(url)
    rerun = rerun_binary()
    if headless:
        if record is None:
            raise ValueError("a headless Rerun server only records: give it a file to record to (--record FILE.rrd)")
        # With --save and no url, `rerun` hosts the gRPC server itself and streams what it receives to the file.
        serve = (rerun, "--save", str(record), "--port", str(port), "--bind", bind, "--server-memory-limit",
                 server_memory_limit)
        return ViewerPlan((serve,), native=False, address=url, headless=True)
    native = not web if web is not None else has_display()
    if native:
        serve = (rerun, "--port", str(port), "--bind", bind, "--memory-limit", viewer_memory_limit,
                 "--server-memory-limit", server_memory_limit, "--hide-welcome-screen")
        address = url
    else:
        serve = (rerun, "--serve-web", "--port", str(port), "--web-viewer-port", str(web_port), "--bind", bind,
                 "--server-memory-limit", server_memory_limit)
        address = web_viewer_address(url, web_port)
    commands = [serve]
    if record is not None:
        # --port 0: the recorder's own listener (every rerun process has one) takes a free port, not the run's.
        commands.append((rerun, url, "--save", str(record), "--port", "0", "--bind", "127.0.0.1"))
    return ViewerPlan(tuple(commands), native, address)
