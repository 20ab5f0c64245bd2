"""What streaming rollouts to Rerun costs an actor: env steps per second with streaming off and on, same run.

One process plays the actor's cycle (the jitted rollout, the batch copied to the host, and with streaming on the
actor's `RolloutStream` offering the watched environments to a `Monitor`) against a real Rerun gRPC server
(`rerun --serve-grpc`, started here as the viewer's stand-in). The modes alternate in rounds so that drift (thermal,
other load) hits them alike:

- off: the rollout compiled without watching, no monitor (monitor.enabled=false);
- on: watching `--watch` environments, streamed at the default rate (monitor.frames_per_s);
- on-every-rollout: every rollout offered (an unlimited rate): what logging costs when nothing is skipped, with
  the drops the bounded queue makes.

Prints one JSON line per mode with env steps/s, the ratio to "off", and the monitor's counters.
"""

from __future__ import annotations

import argparse
import dataclasses
import socket
import subprocess
import time
from pathlib import Path
from typing import Any

import jax

from impulse.benchmarks._harness import REPO, emit, environment, progress

DEFAULT_CONFIG = REPO / "configs" / "quick-launch.toml"
MODES = ("off", "on", "on-every-rollout")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(config_path: Path, overrides: list[str], rounds: int, cycles: int, watch: int) -> list[dict[str, Any]]:
    from impulse.actors.levels import LocalLevels
    from impulse.actors.rollout import rollout, start_rollout
    from impulse.actors.trajectory import make_batch
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig
    from impulse.engine.env.spec import env_from_config
    from impulse.learner.agent import make_agent
    from impulse.monitor.rollouts import RolloutStream
    from impulse.monitor.stream import Monitor, server_reachable
    from impulse.monitor.viewer import rerun_binary

    config = resolve_config(RunConfig, config_path, overrides)
    ppo = config.ppo
    spec, env_params = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    params = agent.init(jax.random.PRNGKey(0))
    levels = LocalLevels(config.env, spec.sizes).next_batch(jax.random.PRNGKey(1)).levels
    rollouts = {w: jax.jit(lambda p, c, w=w: rollout(agent.act, p, spec, env_params, c, levels, ppo.num_steps,
                                                     watch=w), donate_argnums=1) for w in (0, watch)}
    carry = start_rollout(spec, env_params, levels, ppo.num_envs, jax.random.PRNGKey(2))
    for roll in rollouts.values():  # compile both, twice each (weak types)
        for _ in range(2):
            carry = jax.block_until_ready(roll(params, carry).carry)

    port = _free_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    server = subprocess.Popen([rerun_binary(), "--serve-grpc", "--port", str(port), "--bind", "127.0.0.1",
                               "--server-memory-limit", "512MiB"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    rates = {"on": config.monitor.frames_per_s, "on-every-rollout": 1e12}
    monitors = {mode: Monitor(f"bench-{mode}", url=url, frames_per_s=rate, frame_queue=config.monitor.queue_rollouts,
                              probe_every_s=0.2) for mode, rate in rates.items()}
    try:
        deadline = time.monotonic() + 30
        while not (server_reachable(url) and all(m.viewer_up for m in monitors.values())):
            if time.monotonic() > deadline:
                raise RuntimeError("the Rerun server did not come up")
            time.sleep(0.1)
        streams = {mode: RolloutStream(m, f"bench-{mode}", watch, ppo.num_steps) for mode, m in monitors.items()}
        seconds = dict.fromkeys(MODES, 0.0)
        for r in range(rounds):
            for mode in MODES:
                stream = streams.get(mode)
                roll = rollouts[watch if stream is not None else 0]
                start = time.perf_counter()
                for _ in range(cycles):
                    started_at, cycle_start = time.time(), time.perf_counter()
                    carry, steps, train_mask, _, watched = roll(params, carry)
                    batch = jax.device_get(make_batch(steps, carry.obs, 0, train_mask=train_mask))
                    if stream is not None:
                        stream.after_rollout(batch.steps, watched.state, watched.actuation, 0, started_at,
                                             time.perf_counter() - cycle_start)
                seconds[mode] += time.perf_counter() - start
            progress(f"round {r + 1}/{rounds}: " + ", ".join(
                f"{mode} {ppo.num_envs * ppo.num_steps * cycles * (r + 1) / s:,.0f} steps/s"
                for mode, s in seconds.items()))
    finally:
        for monitor in monitors.values():
            monitor.close()
        server.terminate()
        server.wait(10)
    steps_per_mode = ppo.num_envs * ppo.num_steps * cycles * rounds
    base = steps_per_mode / seconds["off"]
    records = []
    for mode in MODES:
        rate = steps_per_mode / seconds[mode]
        counts = monitors[mode].status() if mode in monitors else {}
        records.append({"bench": "monitor", "mode": mode, "env_steps_per_s": round(rate, 1),
                        "ratio_vs_off": round(rate / base, 4), "num_envs": ppo.num_envs, "num_steps": ppo.num_steps,
                        "watch": watch if mode != "off" else 0, "rounds": rounds, "cycles_per_round": cycles,
                        "frames_per_s_limit": rates.get(mode), **{k: v for k, v in counts.items() if k != "viewer"},
                        "network": dataclasses.asdict(config.network)["kind"], **environment()})
    return records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="impulse bench monitor", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                        help="run config (default configs/quick-launch.toml: the actors' shapes of `make run`)")
    parser.add_argument("--rounds", type=int, default=5, help="rounds of the three modes (default 5)")
    parser.add_argument("--cycles", type=int, default=8, help="rollouts per mode per round (default 8)")
    parser.add_argument("--watch", type=int, default=1, help="environments streamed (default 1)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override")
    args = parser.parse_args(argv)
    for record in run(args.config, args.set, args.rounds, args.cycles, args.watch):
        emit(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
