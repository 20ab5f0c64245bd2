"""Does a compiled program fit in the memory it will run in? XLA knows what a compiled program holds at once (its
arguments, outputs and temporaries, `Compiled.memory_analysis`), so a configuration sized for a GPU can be refused
with a number and an override before it runs, instead of being killed by the kernel minutes later. Every process
that compiles a program sized by `ppo.num_envs` x `ppo.num_steps` checks it here: the fused trainer's training step
(`impulse train`), the learner service's update and an actor's rollout (`impulse launch`). In the engine, the
bottom room, so that each of them can use it (it needs only JAX).

What is compared: the program's peak (arguments + outputs + temporaries, less the buffers its outputs reuse) against
the memory free on the device it runs on: on a GPU the allocator's limit, on a CPU the host's available memory
(`MemAvailable`, which counts what the kernel can reclaim). Other live arrays (a second copy of the carry while it is
checkpointed, evaluation programs) come on top, hence the margin.
"""

from __future__ import annotations

import logging
import os
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import jax

log = logging.getLogger(__name__)

MARGIN = 0.8
"""Share of the free memory one compiled program may take."""
HOST_PROCESSES_ENV = "IMPULSE_HOST_PROCESSES"
"""Set by `impulse launch` for its children: how many processes of the run share this host's memory. On a CPU each
plans for that share of what is free (`host_share`), so that the learner and several actors cannot each pass the
check while together needing more than the machine has. On a GPU each process's allocator limit is its share
already (`actors.memory_fraction`)."""


class DoesNotFit(ValueError):
    """A compiled program needs more memory than the device has free (the message says how much, and what to set)."""


def program_bytes(compiled: Any) -> int | None:
    """Peak bytes of a compiled program, or None where the backend does not say."""
    try:
        stats = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - a backend without the analysis: nothing to check
        return None
    if stats is None:
        return None
    return int(stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes
               - stats.alias_size_in_bytes)


def free_bytes(device: jax.Device | None = None) -> int | None:
    """Memory the device can give a program: a GPU's allocator limit less what is in use, or a CPU host's
    available memory; None when unknown."""
    import jax  # here, not at the top: the launcher reads HOST_PROCESSES_ENV without loading JAX

    device = device or jax.devices()[0]
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        if "bytes_limit" in stats:
            return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
        return None
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError):
        return None


def host_share() -> int:
    """How many processes share this host's memory, as `impulse launch` told its children (`HOST_PROCESSES_ENV`);
    1 for a process started alone, or on a GPU."""
    import jax

    if jax.devices()[0].platform != "cpu":
        return 1
    try:
        return max(1, int(os.environ.get(HOST_PROCESSES_ENV, "1")))
    except ValueError:
        return 1


def check_fits(compiled: Any, what: str, num_envs: int, num_steps: int, free: int | None = None) -> None:
    """Raise `DoesNotFit` when `compiled` (`what`, e.g. "the training step": a program over `num_envs` x
    `num_steps` env steps) needs more than `MARGIN` of the free memory (`free_bytes()` unless given; on a CPU shared
    by the processes of a launch, this process's share of it), naming the sizes, the memory needed and free, and the
    override that would fit."""
    import jax

    need = program_bytes(compiled)
    free = free_bytes() if free is None else free
    if need is None or free is None:
        return
    sharing = host_share()
    free //= sharing
    shared = f" (its 1/{sharing} share: {sharing} processes of this run share the host)" if sharing > 1 else ""
    log.info("%s needs %.2f GiB of the %.1f GiB free%s", what, need / 2**30, free / 2**30, shared)
    if need <= MARGIN * free:
        return
    envs = num_envs  # memory grows about linearly with the batch: halve it until it would fit
    while envs > 1 and envs / num_envs > MARGIN * free / need:
        envs //= 2
    raise DoesNotFit(
        f"{what} needs about {need / 2**30:.1f} GiB ({num_envs:,} envs x {num_steps:,} steps per update), more "
        f"than {MARGIN:.0%} of the {free / 2**30:.1f} GiB free on {jax.devices()[0].platform}{shared}; use fewer, for "
        f"example ppo.num_envs={envs} (configs/quick-cpu.toml is sized for a CPU)")


GPU_SIZED_STEPS = 2**17
"""Env steps per update from which a CPU run is warned that its sizes are a GPU's (Kinetix trains at 2,048 x 256)."""


def warn_if_gpu_sized(num_envs: int, num_steps: int) -> None:
    """On a CPU, say before a long compile that GPU-sized updates will be slow (and may not fit)."""
    import jax

    if jax.default_backend() == "cpu" and num_envs * num_steps >= GPU_SIZED_STEPS:
        log.warning("ppo.num_envs x ppo.num_steps = %s x %s env steps per update are GPU sizes: on this CPU one "
                    "update takes minutes; configs/quick-cpu.toml is sized for a CPU", f"{num_envs:,}",
                    f"{num_steps:,}")
