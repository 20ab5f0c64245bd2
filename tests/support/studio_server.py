"""A studio app served by uvicorn on a free loopback port, in a thread of the test's process, with the settings and
the address `impulse studio` uses (`studio.app.UVICORN_SETTINGS`, `studio.security.studio_address`)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, NamedTuple

HOST = "127.0.0.1"


class Served(NamedTuple):
    """A running studio: `base` is `http://127.0.0.1:PORT` (no token), `url` the address `impulse studio` would
    print (the page, with the token), `token` the token (None: the app needs none)."""

    base: str
    url: str
    port: int
    token: str | None


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind((HOST, 0))
        return probe.getsockname()[1]


@contextmanager
def serving(app: Any, token: str | None) -> Iterator[Served]:
    """Serve `app` (built by `make_app(..., token=token)`) until the block ends."""
    import uvicorn

    from impulse.studio.app import UVICORN_SETTINGS
    from impulse.studio.security import studio_address

    port = free_port()
    config = uvicorn.Config(app, host=HOST, port=port, log_config=None, log_level="warning", **UVICORN_SETTINGS)
    served = uvicorn.Server(config)
    thread = threading.Thread(target=served.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not served.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield Served(f"http://{HOST}:{port}", studio_address(HOST, port, token), port, token)
    finally:
        served.should_exit = True
        thread.join(timeout=10)
