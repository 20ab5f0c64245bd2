"""Who may use a studio: the access token, and the checks that keep other web pages out.

- Token. A studio bound to an address other than loopback needs one (`impulse studio --token`); then every HTTP
  request and WebSocket must carry it: as the query parameter `token`, the header `X-Impulse-Token`, or the cookie
  the studio sets when a page is opened with `?token=...` (so the page's own scripts, images and socket carry it
  without putting it in every URL). Compared in constant time.
- Other sites. A page from another origin that the user happens to have open could otherwise drive a studio on
  127.0.0.1: a WebSocket whose `Origin` is not the studio's own is refused (browsers send it on every socket), and
  a POST must say `Content-Type: application/json` (a cross-site form cannot, without a CORS preflight the studio
  never answers).
"""

from __future__ import annotations

import hmac
import json
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs, urlsplit

TOKEN_PARAMETER = "token"
TOKEN_HEADER = b"x-impulse-token"
TOKEN_COOKIE = "impulse_studio_token"
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
POLICY_VIOLATION = 1008  # WebSocket close code


def is_loopback(host: str) -> bool:
    """Whether binding to `host` keeps the studio on this machine."""
    return host in LOOPBACK_HOSTS


def _headers(scope: dict) -> dict[bytes, bytes]:
    return {name.lower(): value for name, value in scope.get("headers", [])}


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
    morsel = cookie.get(TOKEN_COOKIE)
    return (morsel.value if morsel else None), False


def same_origin(scope: dict) -> bool:
    """Whether a WebSocket's `Origin` (if any: non-browser clients send none) names the host it connects to."""
    headers = _headers(scope)
    origin = headers.get(b"origin")
    if origin is None:
        return True
    return urlsplit(origin.decode("latin-1")).netloc == headers.get(b"host", b"").decode("latin-1")


class Guard:
    """ASGI middleware: the token (when set) and the same-origin checks, in front of the whole app."""

    def __init__(self, app: Any, token: str | None = None):
        self.app = app
        self.token = token

    def _token_ok(self, scope: dict) -> tuple[bool, bool]:
        if self.token is None:
            return True, False
        given, in_query = presented_token(scope)
        return given is not None and hmac.compare_digest(given.encode(), self.token.encode()), in_query

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] == "websocket":
            ok, _ = self._token_ok(scope)
            if not ok or not same_origin(scope):
                await send({"type": "websocket.close", "code": POLICY_VIOLATION})
                return
            await self.app(scope, receive, send)
            return
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        ok, in_query = self._token_ok(scope)
        if not ok:
            await _refuse(send, 401, "this studio needs its access token: open the address `impulse studio` "
                                     "printed (it ends in ?token=...), or send the header X-Impulse-Token")
            return
        if scope["method"] == "POST":
            content_type = _headers(scope).get(b"content-type", b"").split(b";")[0].strip().lower()
            if content_type != b"application/json":
                await _refuse(send, 415, "POST requests must send JSON with Content-Type: application/json")
                return
        if not in_query:
            await self.app(scope, receive, send)
            return

        async def send_with_cookie(message: dict) -> None:
            if message["type"] == "http.response.start":
                cookie = f"{TOKEN_COOKIE}={self.token}; Path=/; HttpOnly; SameSite=Strict"
                message = {**message, "headers": [*message.get("headers", []), (b"set-cookie", cookie.encode())]}
            await send(message)

        await self.app(scope, receive, send_with_cookie)


async def _refuse(send: Any, status: int, message: str) -> None:
    body = json.dumps({"error": message}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})
