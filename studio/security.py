"""Who may use a studio, and how much it reads: the Host allow-list, the access token, the same-origin checks and
the request-size cap, all in one ASGI middleware (`Guard`) in front of the whole app.

- Host. Every HTTP request and WebSocket handshake must name, in its `Host` header, one of the studio's own names:
  `localhost`, a loopback address (`127.0.0.1`, `[::1]`), the address it is bound to (`--host`), or a name given
  with `--allow-host` (the port, when present, is not compared, so an SSH tunnel on another port works). Anything
  else is refused with 403 before any other check. This is what stops DNS rebinding: a page of `evil.example`
  whose name the attacker re-points at 127.0.0.1 reaches the studio's socket, but its requests still say
  `Host: evil.example`, so none of them is served.
- Token. `impulse studio` makes a random token at each start (or takes `--token`) and prints it in the address it
  shows (`http://127.0.0.1:PORT/?token=...`). Every HTTP request and WebSocket must carry it: as the query
  parameter `token`, the header `X-Impulse-Token`, or the cookie the studio sets (HttpOnly, SameSite=Strict) on
  any response to a request that had it in the query, so the page's own scripts, images and socket carry it
  without putting it in every URL. The cookie's name ends in the studio's port, so two studios in one browser keep
  their own. Compared in constant time. Without it: 401 (a socket: refused at the handshake).
- Other sites. A page from another origin that the user happens to have open could otherwise drive the studio: a
  WebSocket, or a request other than GET, HEAD or OPTIONS, whose `Origin` is not the studio's own address is
  refused (403); and a POST must say `Content-Type: application/json` (a cross-site form cannot, without a CORS
  preflight the studio never answers). The cookie is SameSite=Strict, so another site's requests do not carry it.
- Size. A request whose `Content-Length` is over the cap is refused with 413 before its body is read; any other
  body is counted while it streams in (`BodyTooLarge` raised from `receive` once the total passes the cap, which
  the app answers with 413), so the studio never holds more than the cap of one request, however it is sent
  (chunked uploads included). Both 413s close the connection, so the rest of the upload is never read. WebSocket
  messages are capped by the server (`ws_max_size`, `studio.app.UVICORN_SETTINGS`).

The `make_app` callers that serve nothing on a socket (Starlette's TestClient) may leave the token out; the Host
check always applies.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import logging
import re
import secrets
from collections.abc import Sequence
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs, quote, urlsplit

log = logging.getLogger(__name__)

TOKEN_PARAMETER = "token"
TOKEN_HEADER = b"x-impulse-token"
TOKEN_COOKIE = "impulse_studio_token"
"""The token cookie's name, followed by `_<port>` when the server reports its port."""
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
POLICY_VIOLATION = 1008  # WebSocket close code
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
"""Methods that change nothing; any other must come from the studio's own page when it names an `Origin`."""
MAX_LOGGED_HOSTS = 64
"""Refused host names logged once each, up to this many (a rebinding page may send thousands of requests)."""

_LABEL = r"[a-z0-9_](?:[a-z0-9_-]{0,61}[a-z0-9_])?"
HOST_NAME = re.compile(rf"{_LABEL}(?:\.{_LABEL})*")
"""A DNS name as the studio compares it: lower case, dot-separated labels, no trailing dot."""
PORT = re.compile(r"[0-9]{1,5}")


def is_loopback(host: str) -> bool:
    """Whether binding to `host` keeps the studio on this machine."""
    return host in LOOPBACK_HOSTS


def new_token() -> str:
    """A fresh random access token (32 random bytes, URL-safe: what `--token` accepts)."""
    return secrets.token_urlsafe(32)


def studio_address(host: str, port: int, token: str | None) -> str:
    """The address `impulse studio` prints: the page at `host:port`, with the token in the query that lets the
    first visit in and sets the cookie."""
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/" + (f"?{TOKEN_PARAMETER}={quote(token, safe='')}" if token else "")


def host_name(value: str) -> str | None:
    """The host a `Host` header (or a `--host` or `--allow-host` value) names, in the form the allow-list compares:
    the port and IPv6 brackets removed, a name in lower case without its trailing dot, an IP address in its
    canonical form. None when it is not a host name or address."""
    value = value.strip()
    if value.startswith("["):  # [v6] or [v6]:port
        inside, closed, rest = value[1:].partition("]")
        if not closed or (rest and not (rest.startswith(":") and PORT.fullmatch(rest[1:]))):
            return None
        try:
            return ipaddress.IPv6Address(inside).compressed
        except ValueError:
            return None
    if value.count(":") > 1:  # a bare IPv6 address (a --host value)
        try:
            return ipaddress.IPv6Address(value).compressed
        except ValueError:
            return None
    name, colon, port = value.partition(":")
    if colon and not PORT.fullmatch(port):
        return None
    name = name.lower().removesuffix(".")
    try:
        return ipaddress.ip_address(name).compressed
    except ValueError:
        pass
    return name if len(name) <= 253 and HOST_NAME.fullmatch(name) else None


def allowed_host_names(bound: str, extra: Sequence[str] = ()) -> frozenset[str]:
    """The host names a studio bound to `bound` answers to: `localhost`, 127.0.0.1 and ::1, `bound` itself and
    `extra` (`--allow-host`), each as `host_name` gives it. (Every loopback address is allowed as well, see
    `host_allowed`.)"""
    names = {host_name(name) for name in (*LOOPBACK_HOSTS, bound, *extra)}
    return frozenset(name for name in names if name is not None)


def host_allowed(name: str | None, allowed: frozenset[str]) -> bool:
    """Whether a request naming host `name` (`host_name` of its Host header) may be served: a name in `allowed` or
    any loopback address (an address cannot be rebound; only a DNS name can)."""
    if name is None:
        return False
    if name in allowed:
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


class BodyTooLarge(ValueError):
    """A request body over the studio's cap: refused with HTTP 413 (and the connection closed) as soon as it is
    known, by its Content-Length or while it streams in."""

    def __init__(self, limit: int, declared: int | None = None):
        said = f"says it is {declared:,} bytes" if declared is not None else "is larger than that"
        super().__init__(f"the request is too large: the studio reads at most {limit:,} bytes and this one {said}")
        self.limit = limit


def _headers(scope: dict) -> dict[bytes, bytes]:
    return {name.lower(): value for name, value in scope.get("headers", [])}


def cookie_name(scope: dict) -> str:
    """The token cookie's name for the server this request reached: `impulse_studio_token_<port>`."""
    server = scope.get("server")
    return f"{TOKEN_COOKIE}_{server[1]}" if server and server[1] is not None else TOKEN_COOKIE


def presented_token(scope: dict) -> tuple[str | None, bool]:
    """(the token a request carries, whether it came in the query string)."""
    query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
    if query.get(TOKEN_PARAMETER):
        return query[TOKEN_PARAMETER][0], True
    headers = _headers(scope)
    if TOKEN_HEADER in headers:
        return headers[TOKEN_HEADER].decode("latin-1"), False
    cookie = SimpleCookie()
    try:
        cookie.load(headers.get(b"cookie", b"").decode("latin-1"))
    except Exception:  # a malformed cookie header carries no token
        return None, False
    morsel = cookie.get(cookie_name(scope))
    return (morsel.value if morsel else None), False


def same_origin(scope: dict) -> bool:
    """Whether a request's `Origin` (if any: non-browser clients send none) names the host it was sent to."""
    headers = _headers(scope)
    origin = headers.get(b"origin")
    if origin is None:
        return True
    return urlsplit(origin.decode("latin-1")).netloc == headers.get(b"host", b"").decode("latin-1")


class Guard:
    """ASGI middleware in front of the whole app: the Host allow-list, the token (when set), the same-origin and
    content-type checks and the body cap, in that order, on every HTTP request and WebSocket handshake.

    `host` is the address the studio is bound to, `allow_hosts` the extra names it answers to, `token` the access
    token (None: none needed; `impulse studio` always gives one), `max_body_bytes` the largest request body read.
    """

    def __init__(self, app: Any, token: str | None = None, host: str = "127.0.0.1",
                 allow_hosts: Sequence[str] = (), max_body_bytes: int = 8 * 2**20):
        self.app = app
        self.token = token
        self.allowed = allowed_host_names(host, allow_hosts)
        self.max_body_bytes = max_body_bytes
        self.logged_hosts: set[str] = set()

    def _token_ok(self, scope: dict) -> tuple[bool, bool]:
        if self.token is None:
            return True, False
        given, in_query = presented_token(scope)
        return given is not None and hmac.compare_digest(given.encode(), self.token.encode()), in_query

    def _host_refusal(self, headers: dict[bytes, bytes]) -> str | None:
        """Why the request's Host is not served, or None when it is allowed."""
        raw = headers.get(b"host")
        if raw is None:
            return "refused: the request has no Host header"
        given = raw.decode("latin-1")
        if host_allowed(host_name(given), self.allowed):
            return None
        shown = given[:100]
        if len(self.logged_hosts) < MAX_LOGGED_HOSTS and shown not in self.logged_hosts:
            self.logged_hosts.add(shown)
            log.warning("studio: refused requests for host %r (not one of its names; --allow-host adds one)", shown)
        return (f"refused: this studio does not answer to the host {shown!r} (it answers to localhost, its "
                f"loopback and bound addresses and its --allow-host names); if that is your name for this "
                f"machine, restart impulse studio with --allow-host {host_name(given) or 'NAME'}")

    def _refusal(self, scope: dict, headers: dict[bytes, bytes]) -> tuple[int, str] | None:
        """(status, reason) when the request or handshake must be refused, else None."""
        host = self._host_refusal(headers)
        if host is not None:
            return 403, host
        if not self._token_ok(scope)[0]:
            return 401, ("this studio needs its access token: open the address `impulse studio` printed (it ends "
                         "in ?token=...), or send the header X-Impulse-Token")
        websocket = scope["type"] == "websocket"
        if (websocket or scope["method"] not in SAFE_METHODS) and not same_origin(scope):
            return 403, "refused: the request comes from a page of another site (its Origin is not this studio)"
        if not websocket and scope["method"] == "POST":
            content_type = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
            if content_type != b"application/json":
                return 415, "POST requests must send JSON with Content-Type: application/json"
        return None

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = _headers(scope)
        refusal = self._refusal(scope, headers)
        if scope["type"] == "websocket":
            if refusal is not None:
                await _deny_socket(receive, send, refusal[1])
            else:
                await self.app(scope, receive, send)
            return
        if refusal is not None:  # the connection closes: a body sent with the request is never read
            await _refuse(send, *refusal, close=True)
            return
        declared = headers.get(b"content-length")
        if declared is not None:
            if not declared.strip().isdigit():
                await _refuse(send, 400, "the Content-Length header is not a number", close=True)
                return
            if int(declared) > self.max_body_bytes:
                await _refuse(send, 413, str(BodyTooLarge(self.max_body_bytes, int(declared))), close=True)
                return
        await self._serve(scope, receive, send)

    async def _serve(self, scope: dict, receive: Any, send: Any) -> None:
        """Run the app with its body capped while it streams in, and the token cookie set when the request had the
        token in its query."""
        in_query = self.token is not None and presented_token(scope)[1]  # checked already: it is the token
        received = 0
        started = False

        async def capped_receive() -> dict:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    raise BodyTooLarge(self.max_body_bytes)
            return message

        async def guarded_send(message: dict) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                if in_query:
                    cookie = f"{cookie_name(scope)}={self.token}; Path=/; HttpOnly; SameSite=Strict"
                    message = {**message, "headers": [*message.get("headers", []), (b"set-cookie", cookie.encode())]}
            await send(message)

        try:
            await self.app(scope, capped_receive, guarded_send)
        except BodyTooLarge as err:  # an app that does not answer it itself (the studio's app does: 413)
            if started:
                raise
            await _refuse(send, 413, str(err), close=True)


async def _refuse(send: Any, status: int, message: str, *, close: bool = False) -> None:
    """Answer an HTTP request with `status` and `{"error": message}` without running the app; `close` ends the
    connection afterwards (an unread body is then never read)."""
    body = json.dumps({"error": message, "problems": []}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(b"connection", b"close")] if close else []
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


async def _deny_socket(receive: Any, send: Any, message: str) -> None:
    """Refuse a WebSocket at its handshake: a close with code 1008 (policy violation) and the reason, before it is
    accepted (uvicorn answers the handshake with HTTP 403; an in-process client sees the close)."""
    connect = await receive()
    if connect["type"] != "websocket.connect":
        return
    reason = message.encode()[:120].decode("utf-8", "ignore")  # a close frame's reason holds 123 bytes
    await send({"type": "websocket.close", "code": POLICY_VIOLATION, "reason": reason})
