"""The bus's configuration sections: `[bus]` (how a process reaches the others) and `[router]` (`impulse
router`: where it listens, which routers it links to, its security). Simple types only: they are sections of the
run's TOML config, checked when it is loaded."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass


def endpoint_parts(endpoint: str) -> tuple[str, str, str]:
    """(protocol, host, port) of a network endpoint such as "tcp/127.0.0.1:7447" or "tcp/[::1]:7447?opt=1", host
    without brackets (for a unix socket's path the parts mean nothing: check the protocol first)."""
    protocol, _, address = endpoint.partition("/")
    host, _, port = address.split("?")[0].rpartition(":")
    return protocol, host.strip("[]"), port


def is_loopback(endpoint: str) -> bool:
    """Whether a listen endpoint is reachable from this machine only (127.x, ::1, localhost, a unix socket)."""
    protocol, host, _ = endpoint_parts(endpoint)
    if protocol.startswith("unixsock"):
        return True
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _check_endpoint(endpoint: object, what: str) -> str:
    if not isinstance(endpoint, str) or "/" not in endpoint or any(ch.isspace() for ch in endpoint):
        raise ValueError(f"{what} {endpoint!r} is not a zenoh endpoint like 'tcp/127.0.0.1:7447'")
    protocol, _, address = endpoint.partition("/")
    if not protocol or not address:
        raise ValueError(f"{what} {endpoint!r} is not a zenoh endpoint like 'tcp/127.0.0.1:7447'")
    return endpoint


def check_positive(name: str, value: object, kind: type | tuple[type, ...]) -> None:
    """Refuse anything but a positive number of `kind` with a ValueError naming `name`."""
    if isinstance(value, bool) or not isinstance(value, kind) or not value > 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")


@dataclass(frozen=True)
class BusConfig:
    """How a process reaches the bus; a section of the run's TOML config, hence only simple types."""

    hub: str = "tcp/127.0.0.1:7447"
    """Endpoint of the one-machine hub: the hub listens on it, every other process connects to it. Loopback only:
    the hub has no authentication (docs/multi-host.md, "The open one-machine bus")."""
    connect: tuple[str, ...] = ()
    """Several machines: the routers to connect to. When non-empty it replaces `hub` for connecting."""
    shared_memory: bool = True
    """Large messages between processes of one machine go through shared memory instead of the socket."""
    shm_pool_mib: int = 64
    """Shared-memory pool per process; a message that does not fit falls back to the socket (keep >= 2x the
    largest message: 16 MiB messages were no faster than TCP with zenoh's default 16 MiB pool)."""
    lease_ms: int = 3000
    """A hung peer (socket open, process stopped) is declared gone after about this long."""
    block_timeout_ms: int = 60000
    """How long a blocking put waits for a full queue before zenoh drops the message (longest receiver pause)."""
    query_timeout_s: float = 10.0
    """Default timeout of `Bus.get`."""
    credentials: str = ""
    """With `connect`: the credentials directory (see `bus.router`) holding `ca.pem` for TLS and this process's
    `<role>.pem`/`.key` (mutual TLS) and `<role>.password` (user/password); empty: plain, unauthenticated."""
    status_every_s: float = 1.0
    """How often each process publishes its status line for `impulse launch`'s display; 0: at every turn of its
    loop (hundreds a second in an idle curriculum service)."""
    wire_compact: bool = False
    """Send trajectories in the compact format (`actors.wire`): booleans as bits, only the entity rows a batch
    uses, exactly (2 to 3 times fewer bytes on the bus), for runs across hosts; it costs the actors and the learner
    several times the padded copy, so on one machine the padded arrays (False) are faster. The actors, the learner
    and the recorder all read it."""
    wire_float16: bool = False
    """With `wire_compact`: observation features as float16 (half the bytes again; the learner widens them back
    to float32, so it trains on inputs rounded to float16's 11 significant bits). False: exact float32."""

    def __post_init__(self) -> None:
        _check_endpoint(self.hub, "bus.hub")
        if not is_loopback(self.hub):
            raise ValueError(f"bus.hub {self.hub!r} is not a loopback address: the one-machine hub has no "
                             "authentication, so it listens on this machine only (127.0.0.1, ::1 or localhost); "
                             "across machines run `impulse router` with credentials and set bus.connect")
        connect = self.connect
        if isinstance(connect, str) or not isinstance(connect, tuple | list):
            raise ValueError(f"bus.connect must be a list of endpoints, got {connect!r}")
        object.__setattr__(self, "connect", tuple(_check_endpoint(e, "bus.connect entry") for e in connect))
        if isinstance(self.status_every_s, bool) or not isinstance(self.status_every_s, int | float) or not (
                self.status_every_s >= 0):
            raise ValueError(f"bus.status_every_s must be at least 0, got {self.status_every_s!r}")
        if self.wire_float16 and not self.wire_compact:
            raise ValueError("bus.wire_float16 is part of the compact format: set bus.wire_compact=true too")
        if not isinstance(self.shared_memory, bool):
            raise ValueError(f"bus.shared_memory must be true or false, got {self.shared_memory!r}")
        check_positive("bus.shm_pool_mib", self.shm_pool_mib, int)
        check_positive("bus.lease_ms", self.lease_ms, int)
        check_positive("bus.block_timeout_ms", self.block_timeout_ms, int)
        check_positive("bus.query_timeout_s", self.query_timeout_s, int | float)


def _check_endpoints(name: str, endpoints: object) -> tuple[str, ...]:
    if isinstance(endpoints, str) or not isinstance(endpoints, tuple | list):
        raise ValueError(f"{name} must be a list of endpoints, got {endpoints!r}")
    for endpoint in endpoints:
        protocol, _, address = str(endpoint).partition("/")
        if not isinstance(endpoint, str) or not protocol or not address or any(c.isspace() for c in endpoint):
            raise ValueError(f"{name} entry {endpoint!r} is not a zenoh endpoint like 'tcp/127.0.0.1:7447'")
    return tuple(endpoints)


@dataclass(frozen=True)
class RouterConfig:
    """`impulse router`: where it listens, which routers it links to, and its security."""

    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    """Endpoints the router listens on. Loopback by default: listen on a host's address (e.g. "tls/0.0.0.0:7447")
    to serve other machines, with credentials."""
    connect: tuple[str, ...] = ()
    """Other routers to link to (one router per host, each host's processes connecting to their own)."""
    credentials: str = ""
    """Credentials directory (see `bus.router`): TLS with `ca.pem`, the router's certificate and, when
    `mutual_tls`, clients' certificates; user/password authentication with `users.txt`. Empty: neither."""
    mutual_tls: bool = True
    """With TLS, clients must present a certificate signed by the CA as well."""
    access_control: bool = True
    """With credentials, allow each role only its part of the protocol (needs an authentication method)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "listen", _check_endpoints("router.listen", self.listen))
        object.__setattr__(self, "connect", _check_endpoints("router.connect", self.connect))
        if not self.listen:
            raise ValueError("router.listen is empty: a router must listen somewhere")
