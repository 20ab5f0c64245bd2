"""Impulse Studio's play latency: the server's step time and the round trip a client sees, over a real socket.

The studio app (`studio.app.make_app`) is served by uvicorn on a free loopback port in a thread of this process; a
`websockets` client (as a page's socket, without a browser) loads one level, takes `--warmup` steps that are not
counted (the first compiles the environment step, or finds it in JAX's cache), then `--steps` steps with a held
action, one at a time: each step is sent, its reply awaited, then the next sent, as the page does. Per step the
reply's `step_ms` (the jitted environment step on the server, device work included) and the client's round trip
(send to reply parsed: socket, JSON both ways, the scene drawn for the reply) are recorded.

With `--agent CHECKPOINT` (a run directory or `pretrained/general-s`) the socket first loads that agent, as the
Play page's "Load agent" does, and every step is the agent's (`{"type": "step", "agent": true}`): watching, whose
server step adds the policy's forward pass and its sampled action.

Prints one JSON line per level with p50/p99/max of both, in milliseconds, and the steps per second the loop held.
What it does not measure: a browser's own event loop and drawing (the Play page shows its own readout).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from impulse.benchmarks._harness import emit, environment, progress

DEFAULT_LEVELS = ("s_hop_over", "s_easy_car_right")
HELD_ACTION = [1, 0, 0, 0, 1, 0]
"""Motor 0 forwards and thruster 0 on, held: the step does the work a person playing makes it do."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _percentiles(values: list[float]) -> dict[str, float]:
    array = np.asarray(values)
    return {"p50": round(float(np.percentile(array, 50)), 3), "p99": round(float(np.percentile(array, 99)), 3),
            "max": round(float(array.max()), 3)}


async def _play(url: str, level: str, warmup: int, steps: int, agent: str | None) -> dict[str, Any]:
    import websockets

    step = {"type": "step", "agent": True} if agent else {"type": "step", "action": HELD_ACTION}
    async with websockets.connect(url, max_size=None) as socket_:
        await socket_.send(json.dumps({"type": "load", "set": "handmade", "name": level}))
        reply = json.loads(await socket_.recv())
        if reply.get("type") != "state":
            raise RuntimeError(f"loading {level} failed: {reply}")
        if agent:
            await socket_.send(json.dumps({"type": "agent", "checkpoint": agent}))
            reply = json.loads(await socket_.recv())
            if reply.get("type") == "error":
                raise RuntimeError(f"loading the agent {agent} failed: {reply['message']}")
        server_ms, round_trip_ms = [], []
        started = time.perf_counter()
        for index in range(warmup + steps):
            if index == warmup:
                started = time.perf_counter()
            sent = time.perf_counter()
            await socket_.send(json.dumps(step))
            reply = json.loads(await socket_.recv())
            if reply.get("type") != "state":
                raise RuntimeError(f"step {index} on {level} failed: {reply}")
            if index >= warmup:
                round_trip_ms.append((time.perf_counter() - sent) * 1e3)
                server_ms.append(float(reply["step_ms"]))
        elapsed = time.perf_counter() - started
    return {"server_step_ms": _percentiles(server_ms), "round_trip_ms": _percentiles(round_trip_ms),
            "steps_per_s": round(steps / elapsed, 1)}


def run(levels: list[str], warmup: int, steps: int, agent: str | None = None) -> list[dict[str, Any]]:
    import uvicorn

    from impulse.deploy.runtime.pilots import load_pilot
    from impulse.studio.app import make_app

    port = _free_port()
    with tempfile.TemporaryDirectory() as saved:
        app = make_app(Path(saved), load_pilot=load_pilot)
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
        thread = threading.Thread(target=server.run, daemon=True)
        thread.start()
        deadline = time.monotonic() + 30
        while not server.started:
            if time.monotonic() > deadline or not thread.is_alive():
                raise RuntimeError("the studio server did not start")
            time.sleep(0.05)
        records = []
        try:
            for level in levels:
                progress(f"studio: {level}, {warmup} warm-up + {steps} steps")
                result = asyncio.run(_play(f"ws://127.0.0.1:{port}/ws/play", level, warmup, steps, agent))
                records.append({"measure": "studio_watch_latency" if agent else "studio_play_latency",
                                "level": level, "agent": agent, "steps": steps, "warmup": warmup,
                                "client": "websockets over loopback to uvicorn", **result, **environment()})
        finally:
            server.should_exit = True
            thread.join(timeout=10)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench studio", description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", nargs="+", default=list(DEFAULT_LEVELS), help="hand-made level names")
    parser.add_argument("--warmup", type=int, default=20, help="steps not counted (the first compiles)")
    parser.add_argument("--steps", type=int, default=300, help="steps measured per level")
    parser.add_argument("--agent", metavar="CHECKPOINT",
                        help="watch: this agent (a run directory or pretrained/general-s) chooses every action")
    args = parser.parse_args(argv)
    for record in run(args.levels, args.warmup, args.steps, args.agent):
        emit(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
