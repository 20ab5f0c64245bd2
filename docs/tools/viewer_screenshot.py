#!/usr/bin/env python3
"""Take a PNG screenshot of the Rerun viewer (0.41) showing a recording, on a headless machine.

Usage::

    python docs/tools/viewer_screenshot.py SOURCE -o OUT.png [--size 1600x1000] [--wait 5] [--method auto|native|web]

SOURCE is an ``.rrd`` file or a live gRPC proxy URL such as ``rerun+http://127.0.0.1:9876/proxy`` (a
``rerun --serve-grpc`` / ``rerun --serve-web`` server that training processes stream into).

Why this exists: docs and reports want pictures of what the viewer shows, and our machines have no display.
``rerun --screenshot-to`` alone is not enough: it fires ten frames after start-up, with no way to wait for a
live stream to arrive, and an ``.rrd`` is caught while it plays from the start of its timeline.

How it works (only the standard library is used; everything else runs as child processes):

* ``native`` (preferred): ``rerun SOURCE --headless`` renders the native viewer offscreen (no X server, no
  Xvfb) through wgpu/Vulkan. On a CPU-only machine that needs Mesa's lavapipe Vulkan driver
  (``apt-get install mesa-vulkan-drivers``); the GL backend does not work on llvmpipe (no R32Float targets).
  The script drives the viewer with ``rerun viewer-mcp`` (JSON-RPC over stdio): it polls ``rerun_get_state``
  until a recording is loaded, runs ``recording.seek_to_end_and_follow`` (end of an ``.rrd``, newest data of
  a live stream), waits ``--wait`` seconds (chunks load, start-up toasts fade), then has the viewer write the
  PNG with ``rerun_save_screenshot``. The image is ``--size`` pixels.
* ``web`` (fallback): ``rerun --serve-web`` hosts the web viewer, headless Chromium renders it with WebGL on
  SwiftShader, and the Chrome DevTools protocol (a minimal websocket client below) waits for the app to
  start, presses Ctrl+Shift+Right (end of timeline and follow), waits ``--wait`` seconds and captures the page.
  ``--virtual-time-budget`` does not work here: compiling the wasm takes real time.
* ``auto``: ``native``, then ``web`` if ``native`` fails for any reason but the data itself (no graphics
  adapter, missing tool, ...).

Every child runs in its own process group, which is killed on success, error, timeout and Ctrl+C
(the venv's ``rerun`` is a Python wrapper that starts the real binary as a grandchild).
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import itertools
import json
import os
import queue
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path
from typing import IO, Any

LIVE_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


class ScreenshotError(RuntimeError):
    """A failure with a message meant for the user."""


class SourceError(ScreenshotError):
    """The data could not be loaded: another method would not do better, so `auto` does not fall back."""


class Children:
    """Starts child processes in their own process groups and kills every group on `close`."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: list[tuple[subprocess.Popen[bytes], Path]] = []

    def start(self, name: str, cmd: list[str], *, pipes: bool = False) -> subprocess.Popen[bytes]:
        log = self.log_dir / f"{name}.log"
        with open(log, "wb") as log_file:
            proc = subprocess.Popen(
                cmd,
                stdin=subprocess.PIPE if pipes else subprocess.DEVNULL,
                stdout=subprocess.PIPE if pipes else log_file,
                stderr=log_file,
                start_new_session=True,
            )
        self.procs.append((proc, log))
        return proc

    def log_tail(self, proc: subprocess.Popen[bytes], lines: int = 15) -> str:
        for p, log in self.procs:
            if p is proc:
                text = re.sub(r"\x1b\[[0-9;]*m", "", log.read_text(errors="replace"))
                keep = [ln for ln in text.splitlines() if ln.strip() and not re.match(r"\s+(\d+: |at )", ln)]
                return "\n".join(keep[-lines:]) if keep else "(no output)"
        return ""

    def close(self) -> None:
        for sig, grace in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            alive = [p for p, _ in self.procs if p.poll() is None or _group_alive(p.pid)]
            for p in alive:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(p.pid, sig)
            deadline = time.monotonic() + grace
            for p in alive:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.wait(timeout=max(0.0, deadline - time.monotonic()))
            while any(_group_alive(p.pid) for p in alive) and time.monotonic() < deadline:
                time.sleep(0.05)
        for p, _ in self.procs:
            for stream in (p.stdin, p.stdout):
                if stream is not None:
                    with contextlib.suppress(OSError):
                        stream.close()


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    return True


def find_rerun() -> str:
    for candidate in (Path(sys.executable).parent / "rerun", Path(__file__).resolve().parents[2] / ".venv/bin/rerun"):
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return str(candidate)
    found = shutil.which("rerun")
    if found:
        return found
    raise ScreenshotError("rerun CLI not found next to python, in .venv or on PATH (pip install rerun-sdk)")


def find_chromium() -> str:
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    raise ScreenshotError("chromium not found on PATH (apt-get install chromium)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for_port(port: int, proc: subprocess.Popen[bytes], children: Children, deadline: float, what: str) -> None:
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise ScreenshotError(f"{what} exited with code {proc.returncode}:\n{children.log_tail(proc)}")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return
        time.sleep(0.1)
    raise ScreenshotError(f"timed out waiting for {what} to listen on port {port}:\n{children.log_tail(proc)}")


def check_png(out: Path) -> None:
    if not out.is_file() or out.read_bytes()[:8] != b"\x89PNG\r\n\x1a\n":
        raise ScreenshotError(f"no PNG was written to {out}")


# --------------------------------------------------------------------------------------------------------------
# native: headless viewer driven by `rerun viewer-mcp`


class McpClient:
    """JSON-RPC over the stdio of `rerun viewer-mcp` (one JSON message per line)."""

    def __init__(self, proc: subprocess.Popen[bytes], children: Children) -> None:
        assert proc.stdin is not None and proc.stdout is not None
        self.proc, self.children = proc, children
        self.ids = itertools.count(1)
        self.lines: queue.Queue[bytes] = queue.Queue()
        threading.Thread(target=self._read, args=(proc.stdout,), daemon=True).start()

    def _read(self, stream: IO[bytes]) -> None:
        for line in stream:
            self.lines.put(line)
        self.lines.put(b"")

    def request(self, method: str, params: dict[str, Any], timeout: float = 30.0) -> dict[str, Any]:
        msg_id = next(self.ids)
        self.notify(method, params, msg_id)
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise ScreenshotError(f"viewer-mcp did not answer {method} within {timeout:.0f}s") from None
            if not line:
                raise ScreenshotError(f"viewer-mcp exited:\n{self.children.log_tail(self.proc)}")
            with contextlib.suppress(ValueError):
                reply = json.loads(line)
                if reply.get("id") == msg_id:
                    if "error" in reply:
                        raise ScreenshotError(f"viewer-mcp {method} failed: {reply['error']}")
                    return dict(reply.get("result", {}))

    def notify(self, method: str, params: dict[str, Any], msg_id: int | None = None) -> None:
        msg: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "params": params}
        if msg_id is not None:
            msg["id"] = msg_id
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(json.dumps(msg).encode() + b"\n")
            self.proc.stdin.flush()
        except OSError as err:
            raise ScreenshotError(f"viewer-mcp is gone:\n{self.children.log_tail(self.proc)}") from err

    def tool(self, name: str, args: dict[str, Any] | None = None) -> dict[str, Any]:
        result = self.request("tools/call", {"name": name, "arguments": args or {}})
        text = "".join(c.get("text", "") for c in result.get("content", []) if c.get("type") == "text")
        if result.get("isError"):
            raise ScreenshotError(f"{name} failed: {text}")
        try:
            return dict(json.loads(text)) if text.strip().startswith("{") else {"text": text}
        except ValueError:
            return {"text": text}


def shot_native(source: str, out: Path, width: int, height: int, wait: float, deadline: float, tmp: Path) -> None:
    rerun = find_rerun()
    children = Children(tmp)
    viewer: subprocess.Popen[bytes] | None = None
    try:
        port = free_port()
        viewer = children.start(
            "viewer",
            [rerun, source, "--headless", "--port", str(port), "--bind", "127.0.0.1",
             "--window-size", f"{width}x{height}", "--hide-welcome-screen"],
        )  # fmt: skip
        wait_for_port(port, viewer, children, deadline, "the headless viewer")
        mcp_proc = children.start("mcp", [rerun, "viewer-mcp", "--endpoint", f"http://127.0.0.1:{port}"], pipes=True)
        mcp = McpClient(mcp_proc, children)
        mcp.request("initialize", {"protocolVersion": "2025-06-18", "capabilities": {},
                                   "clientInfo": {"name": "viewer_screenshot", "version": "1"}})  # fmt: skip
        mcp.notify("notifications/initialized", {})

        # Wait until a recording with data on some timeline is the active one.
        log_seq = 0
        while True:
            if viewer.poll() is not None:
                raise ScreenshotError(f"the viewer exited with code {viewer.returncode}:\n{children.log_tail(viewer)}")
            for entry in mcp.tool("rerun_get_logs", {"after_sequence": log_seq}).get("entries", []):
                log_seq = max(log_seq, int(entry.get("sequence", 0)))
                if entry.get("level") == "ERROR" and "Data source failed" in entry.get("message", ""):
                    raise SourceError(f"the viewer could not load {source}: {entry['message']}")
            state = mcp.tool("rerun_get_state")
            active = state.get("active_store_id")
            recs = [r for r in state.get("recordings", []) if r.get("store_id") == active]
            if recs and any(t.get("time_range") for t in recs[0].get("timelines", [])):
                break
            if time.monotonic() > deadline:
                raise SourceError(f"no recording showed up in the viewer from {source} (is anything streaming?)")
            time.sleep(0.2)

        mcp.tool("rerun_run_command", {"id": "recording.seek_to_end_and_follow"})
        # The headless viewer only paints on demand, and its start-up toasts only age while it paints:
        # keep it busy while waiting so that chunks get fetched and the toasts fade out.
        wait_until = time.monotonic() + wait
        while time.monotonic() < wait_until:
            mcp.tool("rerun_get_state")
            time.sleep(0.2)
        out.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(FileNotFoundError):
            out.unlink()
        mcp.tool("rerun_save_screenshot", {"file_path": str(out), "max_size": 0})
        check_png(out)
    except ScreenshotError as err:
        # A viewer that dies (e.g. no usable graphics adapter) shows up first as a failing MCP call: report the cause.
        if viewer is not None and not isinstance(err, SourceError):
            with contextlib.suppress(subprocess.TimeoutExpired):
                viewer.wait(timeout=2.0)
            if viewer.returncode is not None:
                msg = f"the viewer exited with code {viewer.returncode}:\n{children.log_tail(viewer)}"
                raise ScreenshotError(msg) from err
        raise
    finally:
        children.close()


# --------------------------------------------------------------------------------------------------------------
# web: web viewer in headless Chromium, driven over the DevTools protocol


class DevTools:
    """Just enough of a websocket client (RFC 6455, text frames) to talk to one Chromium page."""

    def __init__(self, ws_url: str, timeout: float) -> None:
        parsed = urllib.parse.urlsplit(ws_url)
        self.sock = socket.create_connection((parsed.hostname or "127.0.0.1", parsed.port or 80), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            f"GET {parsed.path} HTTP/1.1\r\nHost: {parsed.netloc}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
        )
        self.buf = b""
        while b"\r\n\r\n" not in self.buf:
            self.buf += self._recv_some()
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ScreenshotError(f"DevTools websocket handshake failed: {head[:200]!r}")
        self.ids = itertools.count(1)

    def _recv_some(self) -> bytes:
        chunk = self.sock.recv(1 << 16)
        if not chunk:
            raise ScreenshotError("Chromium closed the DevTools connection")
        return chunk

    def _recv_exact(self, n: int) -> bytes:
        while len(self.buf) < n:
            self.buf += self._recv_some()
        data, self.buf = self.buf[:n], self.buf[n:]
        return data

    def _send(self, payload: bytes) -> None:
        n = len(payload)
        if n < 126:
            header = struct.pack(">BB", 0x81, 0x80 | n)
        elif n < 1 << 16:
            header = struct.pack(">BBH", 0x81, 0x80 | 126, n)
        else:
            header = struct.pack(">BBQ", 0x81, 0x80 | 127, n)
        mask = os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(header + mask + masked)

    def _recv_message(self) -> dict[str, Any]:
        message = b""
        while True:
            b0, b1 = self._recv_exact(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._recv_exact(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._recv_exact(8))[0]
            if b1 & 0x80:
                self._recv_exact(4)  # servers do not mask, but skip a mask if one is there
            payload = self._recv_exact(n)
            opcode = b0 & 0x0F
            if opcode in (0x8, 0x9, 0xA):  # close, ping, pong: nothing to answer for our short session
                if opcode == 0x8:
                    raise ScreenshotError("Chromium closed the DevTools connection")
                continue
            message += payload
            if b0 & 0x80:
                return dict(json.loads(message))

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        msg_id = next(self.ids)
        self._send(json.dumps({"id": msg_id, "method": method, "params": params}).encode())
        while True:
            reply = self._recv_message()
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise ScreenshotError(f"DevTools {method} failed: {reply['error']}")
                return dict(reply.get("result", {}))

    def evaluate(self, expression: str) -> Any:
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True).get("result", {}).get("value")

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


def shot_web(source: str, out: Path, width: int, height: int, wait: float, deadline: float, tmp: Path) -> None:
    rerun = find_rerun()
    chromium = find_chromium()
    children = Children(tmp)
    devtools: DevTools | None = None
    try:
        web_port = free_port()
        cmd = [rerun, "--serve-web", "--web-viewer-port", str(web_port), "--bind", "127.0.0.1"]
        if source.startswith(LIVE_SCHEMES):
            data_url = source  # the browser connects to the proxy itself; rerun only hosts the viewer
            cmd += [source]
        else:
            grpc_port = free_port()
            data_url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"  # rerun replays the file from its own proxy
            cmd += ["--port", str(grpc_port), source]
        server = children.start("web-server", cmd)
        wait_for_port(web_port, server, children, deadline, "the rerun web server")

        profile = tmp / "chromium-profile"
        browser = children.start(
            "chromium",
            [chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--ignore-gpu-blocklist", "--no-first-run", "--no-default-browser-check", "--mute-audio",
             "--hide-scrollbars", f"--window-size={width},{height}", f"--user-data-dir={profile}",
             "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0", "about:blank"],
        )  # fmt: skip
        port_file = profile / "DevToolsActivePort"
        while not (port_file.is_file() and port_file.read_text().strip()):
            if browser.poll() is not None:
                raise ScreenshotError(f"chromium exited with code {browser.returncode}:\n{children.log_tail(browser)}")
            if time.monotonic() > deadline:
                raise ScreenshotError("timed out waiting for chromium's DevTools port")
            time.sleep(0.1)
        devtools_port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{devtools_port}/json/list", timeout=10) as resp:
            pages = [t for t in json.load(resp) if t.get("type") == "page"]
        if not pages:
            raise ScreenshotError("chromium has no page to drive")
        devtools = DevTools(pages[0]["webSocketDebuggerUrl"], timeout=max(10.0, deadline - time.monotonic()))
        devtools.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                      mobile=False)  # fmt: skip
        devtools.call("Emulation.setEmulatedMedia", features=[{"name": "prefers-color-scheme", "value": "dark"}])
        viewer_url = f"http://127.0.0.1:{web_port}/?url={urllib.parse.quote(data_url, safe='')}"
        devtools.call("Page.navigate", url=viewer_url)

        # The page shows "Loading…" text until the wasm app has started and replaced it with its canvas.
        started = "!!document.querySelector('canvas') && !/Loading|Downloading/.test(document.body.innerText)"
        while not devtools.evaluate(started):
            if time.monotonic() > deadline:
                raise ScreenshotError("timed out waiting for the web viewer to start")
            time.sleep(0.25)
        time.sleep(2.0)  # let the first data arrive before seeking
        devtools.evaluate("document.querySelector('canvas').focus()")
        for kind in ("rawKeyDown", "keyUp"):  # Ctrl+Shift+Right: go to the end of the timeline and follow
            devtools.call("Input.dispatchKeyEvent", type=kind, key="ArrowRight", code="ArrowRight",
                          windowsVirtualKeyCode=39, nativeVirtualKeyCode=39, modifiers=2 | 8)  # fmt: skip
        time.sleep(wait)
        data = devtools.call("Page.captureScreenshot", format="png")["data"]
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(base64.b64decode(data))
        check_png(out)
    finally:
        if devtools is not None:
            devtools.close()
        children.close()


# --------------------------------------------------------------------------------------------------------------


def _raise_exit(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("source", help="an .rrd file, or a live proxy URL like rerun+http://127.0.0.1:9876/proxy")
    parser.add_argument("-o", "--output", required=True, type=Path, help="where to write the PNG")
    parser.add_argument("--size", default="1600x1000", help="viewer size in pixels, WIDTHxHEIGHT (default 1600x1000)")
    parser.add_argument("--wait", type=float, default=5.0,
                        help="seconds to wait after the data has loaded, before the capture (default 5)")  # fmt: skip
    parser.add_argument("--method", choices=("auto", "native", "web"), default="auto")
    timeout_help = "give up if the viewer or the data is not up after this many seconds (default 120)"
    parser.add_argument("--timeout", type=float, default=120.0, help=timeout_help)
    args = parser.parse_args(argv)

    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        parser.error(f"--size must look like 1600x1000, not {args.size!r}")
    source: str = args.source
    if not source.startswith(LIVE_SCHEMES):
        path = Path(source)
        if not path.is_file():
            parser.error(f"{source} is neither an existing file nor a rerun:// / rerun+http(s):// URL")
        source = str(path.resolve())
    out = args.output.resolve()

    signal.signal(signal.SIGTERM, _raise_exit)
    signal.signal(signal.SIGHUP, _raise_exit)
    methods = {"native": shot_native, "web": shot_web}
    order = ["native", "web"] if args.method == "auto" else [args.method]
    errors: list[str] = []
    for name in order:
        t0 = time.monotonic()
        try:
            with tempfile.TemporaryDirectory(prefix="viewer_screenshot_") as tmp:
                methods[name](source, out, width, height, args.wait, t0 + args.timeout, Path(tmp))
        except ScreenshotError as err:
            errors.append(f"[{name}] {err}")
            print(f"viewer_screenshot: {name} method failed: {err}", file=sys.stderr)
            if isinstance(err, SourceError):
                break
            continue
        print(f"viewer_screenshot: wrote {out} ({name}, {time.monotonic() - t0:.1f}s)", file=sys.stderr)
        return 0
    if any(word in e for e in errors for word in ("adapter", "render context", "graphics")):
        print("hint: without a GPU the native viewer needs Mesa's lavapipe: apt-get install mesa-vulkan-drivers",
              file=sys.stderr)  # fmt: skip
    return 1


if __name__ == "__main__":
    sys.exit(main())
