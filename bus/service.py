"""A process's work as its run loop drives it: the contract between every long-running role (learner, actor,
curriculum service, the fused trainer) and `deploy`'s one run loop, which owns the stop signal, the checkpoint
cadence, the metrics window, metrics.jsonl and the progress line.

It sits in `bus` because every role is a process on the bus and the rooms that implement it (curriculum, actors,
learner) all stand on `bus`; it is a Protocol, so they implement it without importing the loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol


@dataclass
class CycleReport:
    """What one cycle of a service did."""

    env_steps: int = 0
    """Environment steps produced (actors, fused) or consumed (learner) in this cycle."""
    updates: int = 0
    """Units of progress that drive the checkpoint cadence: parameter updates (trainers), result messages
    applied (the curriculum service)."""
    metrics: dict[str, float] = field(default_factory=dict)
    """Per-cycle values for metrics.jsonl; `episodes`, `solved` and `return_sum` feed the window."""


@dataclass(frozen=True)
class Progress:
    """Where a service stands when the loop starts driving it (a resumed run goes on from its checkpoint) and
    where it ends."""

    env_steps_done: int = 0
    updates_done: int = 0
    total_env_steps: int = 0
    """The run's goal in environment steps, for the progress line; 0: no goal (a service that runs until stopped)."""


class Service(Protocol):
    """One process's work as the run loop drives it. The constructor assembles (restores a checkpoint, opens its
    bus entities); `start` begins the work, under the loop's stop signal and with `close` guaranteed after it. A
    service may also define `request_stop()`, which the loop calls as soon as a stop signal arrives (the actor uses
    it to stop waiting for levels)."""

    def start(self) -> None:
        """Begin: what must happen once before the first cycle and may take long or talk to peers (the first
        weights published, the first levels fetched, a compile that must not delay the first query)."""

    def progress(self) -> Progress:
        """Where the service stands now (read once, when the loop starts)."""

    def cycle(self) -> CycleReport | None:
        """Do one unit of work; None when there was nothing to do (the loop then waits briefly)."""

    def save(self, summary: dict[str, float]) -> None:
        """Write a checkpoint (a service without state to keep does nothing); `summary` is the metrics window's."""

    def finished(self) -> bool:
        """Whether the run's goal is reached."""

    def close(self) -> None:
        """Release what the service holds (wait for checkpoints, say goodbye on the bus); called once, last."""
