"""Copies and time on the bus path of one trajectory-sized message (~17 MB): encode, hand to zenoh, put ->
receive over loopback with shared memory on and off, copy out of zenoh, decode, schema check.

Prints one JSON line per measurement: {"bench": "bus", "what": ..., "bytes": ..., "ms": ..., "copies": ...}
(median of the repeats; `copies` counts full copies of the payload). Copies made inside zenoh cannot be observed
from Python; they are inferred from timings against a plain memcpy of the same size and marked
"copies_basis": "inferred". Put -> receive runs in two processes (this one listens, a receiver process started
with --receiver connects); latency is measured one message at a time with the receiver's acknowledgement, and
throughput with back-to-back puts (BLOCK, receiver FIFO of 4).

    python -m impulse.benchmarks.bus_copies                    # 128 steps x 256 envs x 128 obs floats
    python -m impulse.benchmarks.bus_copies --repeats 5 --burst 10
"""

from __future__ import annotations

import argparse
import contextlib
import json
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import zenoh

from impulse.benchmarks._harness import REPO
from impulse.bus.codec import Kind, decode, encode
from impulse.bus.config import BusConfig
from impulse.bus.schema import Schema, check
from impulse.bus.session import Bus

RUN = "bench-bus"
ACK_TIMEOUT_S = 30.0


def emit(record: dict[str, Any]) -> None:
    print(json.dumps({"bench": "bus", **record}), flush=True)


def trajectory(steps: int, envs: int, obs: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "obs": rng.standard_normal((steps, envs, obs), dtype=np.float32),
        "action": rng.integers(0, 3, (steps, envs, 6), dtype=np.int8),
        "logp": rng.standard_normal((steps, envs), dtype=np.float32),
        "value": rng.standard_normal((steps, envs), dtype=np.float32),
        "reward": rng.standard_normal((steps, envs), dtype=np.float32),
        "done": rng.random((steps, envs)) < 0.01,
        "level_id": rng.integers(0, 2**40, (steps, envs), dtype=np.int64),
    }


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - start)
    return statistics.median(runs) * 1e3


def local_measurements(arrays: dict[str, np.ndarray], repeats: int) -> bytearray:
    frame = encode(Kind.TRAJECTORY, arrays, run=RUN)
    size = len(frame)
    scratch = np.empty(size, np.uint8)
    source = np.frombuffer(frame, np.uint8)
    emit(
        {
            "what": "memcpy (reference for one copy)",
            "bytes": size,
            "copies": 1,
            "ms": median_ms(lambda: np.copyto(scratch, source), repeats),
        }
    )
    emit(
        {
            "what": "encode (arrays -> one bytearray)",
            "bytes": size,
            "copies": 1,
            "copies_basis": "counted",
            "ms": median_ms(lambda: encode(Kind.TRAJECTORY, arrays, run=RUN), repeats),
        }
    )
    emit(
        {
            "what": "bytes(frame) (avoided: encode returns the bytearray)",
            "bytes": size,
            "copies": 1,
            "ms": median_ms(lambda: bytes(frame), repeats),
        }
    )
    emit(
        {
            "what": "zenoh.ZBytes(bytearray) (inside put)",
            "bytes": size,
            "copies": 1,
            "copies_basis": "inferred",
            "ms": median_ms(lambda: zenoh.ZBytes(frame), repeats),
        }
    )
    frozen = bytes(frame)
    emit(
        {
            "what": "zenoh.ZBytes(bytes) (same cost: no zero-copy path)",
            "bytes": size,
            "copies": 1,
            "copies_basis": "inferred",
            "ms": median_ms(lambda: zenoh.ZBytes(frozen), repeats),
        }
    )
    zbytes = zenoh.ZBytes(frame)
    emit(
        {
            "what": "ZBytes.to_bytes (Inbox receive copy)",
            "bytes": size,
            "copies": 1,
            "copies_basis": "counted",
            "ms": median_ms(zbytes.to_bytes, repeats),
        }
    )
    emit(
        {
            "what": "decode (zero-copy views)",
            "bytes": size,
            "copies": 0,
            "copies_basis": "counted",
            "ms": median_ms(lambda: decode(frozen, run=RUN), repeats),
        }
    )
    schema = Schema.from_example(Kind.TRAJECTORY, arrays, leading=("T", "E"), finite=True)
    message = decode(frozen, run=RUN)
    emit(
        {
            "what": "schema check (shapes + NaN/Inf scan of float arrays)",
            "bytes": size,
            "copies": 0,
            "ms": median_ms(lambda: check(message, schema), repeats),
        }
    )
    return frame


def free_endpoint() -> str:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{sock.getsockname()[1]}"


def run_receiver(endpoint: str, shared_memory: bool) -> None:
    """Receive frames on traj/*; acknowledge each on credit/bench with the receive and decode timestamps."""
    config = BusConfig(hub=endpoint, shared_memory=shared_memory)
    with Bus(config, RUN, "learner", "0") as bus:
        subscriber = bus.session.declare_subscriber(bus.keys.traj_all, zenoh.handlers.FifoChannel(4))
        acks = bus.publisher(bus.keys.credit("bench"))
        while True:
            sample = subscriber.recv()
            via_shm = sample.payload.as_shm() is not None
            payload = sample.payload.to_bytes()
            received_ns = time.monotonic_ns()
            if not payload:
                break  # the sender's "done"
            decode(payload, run=RUN)
            decoded_ns = time.monotonic_ns()
            ack = {"received_ns": received_ns, "decoded_ns": decoded_ns, "via_shm": via_shm, "bytes": len(payload)}
            acks.put(json.dumps(ack).encode())
        subscriber.undeclare()


def timed_put(publisher: Any, acks: Any, frame: bytes | bytearray) -> dict[str, Any]:
    """Put one frame and wait for the receiver's acknowledgement: its fields (`received_ns`, `decoded_ns`,
    `via_shm`) plus `sent_ns`, all on this machine's monotonic clock."""
    sent_ns = time.monotonic_ns()
    publisher.put(frame)
    ack = acks.wait(ACK_TIMEOUT_S)
    if ack is None:
        raise RuntimeError("no acknowledgement from the receiver")
    return {**json.loads(ack.payload), "sent_ns": sent_ns}


@contextlib.contextmanager
def receiver_link(bus: Bus, endpoint: str, shared_memory: bool, capacity: int) -> Iterator[tuple[Any, Any]]:
    """The acknowledging receiver (`--receiver`) in a process of its own, linked to `bus`: yields (publisher of
    frames, inbox of acknowledgements); on the way out the receiver is told to stop, and killed if it does not."""
    receiver = subprocess.Popen([sys.executable, "-m", "impulse.benchmarks.bus_copies", "--receiver", endpoint, "--shm",
                                 str(int(shared_memory))], cwd=REPO)
    try:
        acks = bus.inbox(bus.keys.credit("bench"), capacity)
        publisher = bus.publisher(bus.keys.traj("bench"))
        if not Bus.wait_matching(publisher, ACK_TIMEOUT_S):
            raise RuntimeError("the receiver process never subscribed")
        yield publisher, acks
        publisher.put(b"")
        receiver.wait(timeout=ACK_TIMEOUT_S)
    finally:
        if receiver.poll() is None:
            receiver.kill()
            receiver.wait()


def transfer_measurements(frame: bytearray, shared_memory: bool, repeats: int, burst: int) -> None:
    endpoint = free_endpoint()
    config = BusConfig(hub=endpoint, shared_memory=shared_memory)
    label = "shm on" if shared_memory else "shm off"
    with Bus(config, RUN, "actor", "bench", listen=True) as bus, receiver_link(bus, endpoint, shared_memory,
                                                                               burst + 1) as (publisher, acks):
        latencies, decodes, via_shm = [], [], []
        for _ in range(repeats + 1):  # the first is a warm-up
            fields = timed_put(publisher, acks, frame)
            latencies.append((fields["received_ns"] - fields["sent_ns"]) / 1e6)
            decodes.append((fields["decoded_ns"] - fields["received_ns"]) / 1e6)
            via_shm.append(fields["via_shm"])
        # Inferred from the timings below: with shared memory, ZBytes copy + copy into the pool + to_bytes; over
        # the socket, ZBytes copy + batch serialisation + reassembly + to_bytes (plus the kernel's own copies).
        copies = 3 if shared_memory else 4
        emit(
            {
                "what": f"put -> received as bytes, one at a time ({label})",
                "bytes": len(frame),
                "ms": statistics.median(latencies[1:]),
                "copies": copies,
                "copies_basis": "inferred",
                "through_shm": f"{sum(via_shm[1:])}/{len(via_shm) - 1}",
            }
        )
        emit(
            {
                "what": f"decode in the receiver ({label})",
                "bytes": len(frame),
                "ms": statistics.median(decodes[1:]),
                "copies": 0,
                "copies_basis": "counted",
            }
        )
        start = time.perf_counter()
        for _ in range(burst):
            publisher.put(frame)
        received = 0
        while received < burst and acks.wait(ACK_TIMEOUT_S) is not None:
            received += 1
        elapsed = time.perf_counter() - start
        emit(
            {
                "what": f"back-to-back puts, per message ({label})",
                "bytes": len(frame),
                "ms": elapsed / burst * 1e3,
                "copies": copies,
                "copies_basis": "inferred",
                "gb_per_s": round(len(frame) * burst / elapsed / 1e9, 3),
                "received": received,
                "sent": burst,
            }
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=128)
    parser.add_argument("--envs", type=int, default=256)
    parser.add_argument("--obs", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--burst", type=int, default=30, help="messages in the throughput run")
    parser.add_argument("--receiver", help=argparse.SUPPRESS)
    parser.add_argument("--shm", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.receiver:
        run_receiver(args.receiver, bool(args.shm))
        return
    frame = local_measurements(trajectory(args.steps, args.envs, args.obs), args.repeats)
    for shared_memory in (True, False):
        transfer_measurements(frame, shared_memory, args.repeats, args.burst)


if __name__ == "__main__":
    main()
