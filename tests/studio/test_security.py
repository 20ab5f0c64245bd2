"""The studio's guard over real HTTP: a studio served by uvicorn on a loopback port (in a thread of this process, with
`impulse studio`'s server settings and a fresh token, its extra host name given as `--allow-host` parses it),
driven with `http.client` and raw sockets so that every header, the Host included, is what the test says.

- DNS rebinding: a request or WebSocket handshake naming another host (`Host: evil.example:PORT`) is refused with
  403 before anything else, even with the right token, and changes nothing; the studio's own names and the
  `--allow-host` name are served.
- The token: a POST or a WebSocket without it, or with a wrong one, is refused; with it in the query, the header or
  the cookie that the first page load sets (HttpOnly, SameSite=Strict), it is served.
- The size cap: a huge Content-Length is refused at once without the body being sent; a chunked upload of a
  gigabyte is refused with 413 soon after it passes the 8 MiB cap, the connection closed, and this process (the
  server's) grows by far less than the upload; a WebSocket message over the cap closes the socket.
- A save that cannot be written is one 507 naming the file and the free space, and leaves no file behind.

No engine compilation: every refusal happens before the app, and the saves load an S level file.
"""

from __future__ import annotations

import http.client
import json
import select
import socket
import time
from pathlib import Path

import pytest

from impulse.deploy.cli import build_parser
from impulse.engine.levels import handmade
from impulse.studio.app import MAX_BODY_BYTES, make_app
from impulse.studio.security import TOKEN_COOKIE, new_token
from tests.support.studio_server import Served, serving

CAR = "s_easy_car_right"
EXTRA_HOST = "studio.test"
EVIL = "evil.example"
HANDSHAKE = {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Version": "13",
             "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ=="}
GIGABYTE = 2**30


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> tuple[Served, Path]:
    """(the served studio, its levels folder), started as `impulse studio --allow-host studio.test` starts it."""
    pytest.importorskip("uvicorn")
    levels_dir = tmp_path_factory.mktemp("studio-levels")
    args = build_parser().parse_args(["studio", "--levels-dir", str(levels_dir), "--allow-host", EXTRA_HOST])
    token = new_token()
    app = make_app(args.levels_dir, token=token, host=args.host, allow_hosts=args.allow_host)
    with serving(app, token) as served:
        yield served, levels_dir


def call(studio: Served, method: str, path: str, headers: dict[str, str] | None = None,
         body: bytes | None = None, host: str | None = None) -> tuple[int, dict[str, str], bytes]:
    """(status, headers, body) of one request; `host` replaces the Host header (default 127.0.0.1:PORT)."""
    connection = http.client.HTTPConnection("127.0.0.1", studio.port, timeout=30)
    try:
        connection.request(method, path, body=body,
                           headers={"Host": f"127.0.0.1:{studio.port}" if host is None else host, **(headers or {})})
        response = connection.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        connection.close()


def post(studio: Served, path: str, body: dict, headers: dict[str, str] | None = None,
         host: str | None = None) -> tuple[int, dict]:
    status, _, raw = call(studio, "POST", path, {"Content-Type": "application/json", **(headers or {})},
                          json.dumps(body).encode(), host)
    return status, json.loads(raw)


def with_token(studio: Served) -> dict[str, str]:
    return {"X-Impulse-Token": studio.token}


def handshake(studio: Served, path: str = "/ws/play", headers: dict[str, str] | None = None,
              host: str | None = None) -> int:
    """The HTTP status a WebSocket handshake gets: 101 when the socket opens, 403 when the studio refuses it (it
    closes the socket before accepting it, with code 1008, which uvicorn answers with 403)."""
    return call(studio, "GET", path, {**HANDSHAKE, **(headers or {})}, host=host)[0]


def car_level() -> dict:
    return json.loads(handmade.level_file(CAR).read_text())


def test_a_rebinding_host_is_refused_before_anything_and_changes_nothing(studio) -> None:
    served, levels_dir = studio
    evil = f"{EVIL}:{served.port}"
    status, headers, raw = call(served, "GET", "/api/sets", with_token(served), host=evil)
    assert status == 403 and "--allow-host" in json.loads(raw)["error"], raw
    status, headers, _ = call(served, "GET", f"/?token={served.token}", host=evil)
    assert status == 403 and "set-cookie" not in headers  # the token in the query earns no cookie either

    # The live knobs: the studio has no run, so a request it served would be 409; the rebinding one is 403.
    origin = {**with_token(served), "Origin": f"http://{evil}"}
    assert post(served, "/api/curriculum/knobs", {"set": ["replay_prob=0.03"]}, origin, host=evil)[0] == 403
    assert post(served, "/api/curriculum/knobs", {"set": ["replay_prob=0.03"]}, with_token(served))[0] == 409
    status, reply = post(served, "/api/save", {"name": "rebound", "level": car_level()}, origin, host=evil)
    assert status == 403 and not (levels_dir / "rebound.json").exists(), reply

    assert handshake(served, f"/ws/play?token={served.token}", host=evil) == 403
    assert handshake(served, f"/ws/play?token={served.token}", {"Origin": f"http://{evil}"}, host=evil) == 403
    assert handshake(served, f"/ws/play?token={served.token}") == 101

    for name in ("localhost", "127.0.0.1", "[::1]", EXTRA_HOST, EXTRA_HOST.upper() + "."):
        for host in (name, f"{name}:{served.port}"):
            assert call(served, "GET", "/api/sets", with_token(served), host=host)[0] == 200, host
    assert handshake(served, f"/ws/play?token={served.token}", host=f"{EXTRA_HOST}:{served.port}") == 101
    for host in ("127.0.0.1.evil.example", "localhost.evil.example", "studio.test.evil.example", "", "[::1",
                 "127.0.0.1:port"):
        assert call(served, "GET", "/api/sets", with_token(served), host=host)[0] in (400, 403), host


def test_every_post_and_socket_needs_the_token_from_the_query_the_header_or_the_cookie(studio) -> None:
    served, _ = studio
    level = {"level": car_level()}
    assert post(served, "/api/validate", level)[0] == 401
    assert post(served, "/api/validate", level, {"X-Impulse-Token": "not-the-token"})[0] == 401
    assert call(served, "GET", "/")[0] == 401
    assert handshake(served) == 403
    assert handshake(served, "/ws/play?token=not-the-token") == 403

    status, headers, page = call(served, "GET", f"/?token={served.token}")  # the printed address's first visit
    assert status == 200 and b"<html" in page.lower()
    cookie = headers["set-cookie"]
    name = f"{TOKEN_COOKIE}_{served.port}"
    assert cookie.startswith(f"{name}={served.token};") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    assert served.url == f"http://127.0.0.1:{served.port}/?token={served.token}"

    by_cookie = {"Cookie": f"{name}={served.token}"}
    assert post(served, "/api/validate", level, with_token(served))[0] == 200
    status, reply = post(served, "/api/validate", level, by_cookie)
    assert status == 200 and reply["valid"] is True, reply
    assert post(served, f"/api/validate?token={served.token}", level)[0] == 200
    assert post(served, "/api/validate", level, {"Cookie": f"{TOKEN_COOKIE}_1={served.token}"})[0] == 401
    assert handshake(served, headers=by_cookie) == 101
    assert handshake(served, headers=with_token(served)) == 101
    assert handshake(served, f"/ws/play?token={served.token}") == 101
    assert handshake(served, f"/ws/play?token={served.token}", {"Origin": "http://other.example"}) == 403
    # A POST that is not JSON (what a cross-site form sends) is still refused, token or not.
    assert call(served, "POST", "/api/validate", {**with_token(served), "Content-Type": "text/plain"}, b"{}")[0] == 415


def resident_kb(field: str) -> int:
    """This process's (the server's) VmRSS or VmHWM, in kB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise AssertionError(f"no {field} in /proc/self/status")


def chunked_upload(served: Served, total: int, chunk: int = 2**20) -> tuple[bytes, int]:
    """Stream `total` bytes to /api/save as a chunked body (no Content-Length), a chunk at a time, until the
    server answers or stops reading. Returns (the response's bytes, the body bytes sent)."""
    sock = socket.create_connection(("127.0.0.1", served.port), timeout=20)
    piece = b"%x\r\n" % chunk + b" " * chunk + b"\r\n"
    sent = 0
    try:
        sock.sendall(f"POST /api/save HTTP/1.1\r\nHost: 127.0.0.1:{served.port}\r\nX-Impulse-Token: {served.token}"
                     "\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n".encode())
        try:
            while sent < total and not select.select([sock], [], [], 0)[0]:
                sock.sendall(piece)
                sent += chunk
            if sent >= total:
                sock.sendall(b"0\r\n\r\n")  # the whole body went: end it
        except (BrokenPipeError, ConnectionResetError, TimeoutError):  # the server closed, or stopped reading
            pass
        reply = b""
        while b"\r\n\r\n" not in reply:
            try:
                data = sock.recv(65536)
            except (ConnectionResetError, TimeoutError):
                break
            if not data:
                break
            reply += data
        return reply, sent
    finally:
        sock.close()


def test_a_huge_body_is_refused_while_it_streams_without_being_held(studio) -> None:
    served, levels_dir = studio
    started = time.monotonic()
    status, headers, raw = call(served, "POST", "/api/save", {**with_token(served), "Content-Type":
                                                               "application/json", "Content-Length": str(GIGABYTE)})
    assert status == 413 and time.monotonic() - started < 5, raw  # answered with no body sent
    assert f"{MAX_BODY_BYTES:,}" in json.loads(raw)["error"] and headers.get("connection") == "close"

    Path("/proc/self/clear_refs").write_text("5")  # restart the peak-RSS count (VmHWM) from now
    before = resident_kb("VmRSS")
    started = time.monotonic()
    reply, sent = chunked_upload(served, GIGABYTE)
    elapsed = time.monotonic() - started
    grown_mb = (resident_kb("VmHWM") - before) / 1024
    assert reply.startswith(b"HTTP/1.1 413 "), reply[:200]
    assert b"at most 8,388,608 bytes" in reply
    assert sent < 64 * 2**20, f"the server kept reading: {sent:,} bytes were sent"
    assert elapsed < 10, elapsed
    assert grown_mb < 100, f"the studio's resident memory peaked {grown_mb:.0f} MB above its start"
    assert call(served, "GET", "/api/sets", with_token(served))[0] == 200  # and the studio goes on
    assert not list(levels_dir.iterdir())


def test_a_websocket_message_over_the_cap_closes_the_socket(studio) -> None:
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    served, _ = studio
    with connect(f"ws://127.0.0.1:{served.port}/ws/play?token={served.token}", max_size=None) as socket_:
        socket_.send(json.dumps({"type": "reset"}))
        assert "no level loaded" in json.loads(socket_.recv(timeout=30))["message"]
        with pytest.raises(ConnectionClosed) as closed:
            socket_.send(" " * (MAX_BODY_BYTES + 1))
            socket_.recv(timeout=30)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009  # "message too big"


def test_a_save_that_cannot_be_written_is_one_clear_error_and_leaves_no_file(studio) -> None:
    served, levels_dir = studio
    (levels_dir / "blocked.json").mkdir()  # a real failure to replace the file: a folder in its place
    status, reply = post(served, "/api/save", {"name": "blocked", "level": car_level()}, with_token(served))
    assert status == 507, reply
    assert reply["error"].startswith(f"cannot write {levels_dir / 'blocked.json'}: ") and "MB free" in reply["error"]
    assert sorted(path.name for path in levels_dir.iterdir()) == ["blocked.json"]  # no temporary file left
    (levels_dir / "blocked.json").rmdir()
    status, reply = post(served, "/api/save", {"name": "blocked", "level": car_level()}, with_token(served))
    assert status == 200 and (levels_dir / "blocked.json").is_file(), reply
