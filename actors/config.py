"""The `[actors]` section: actor processes of a distributed run (how many, credits, devices, status cadence)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from impulse.engine.config_checks import check_device_list, check_range


@dataclass(frozen=True)
class ActorConfig:
    """Actor processes of a distributed run. Each actor rolls out `ppo.num_envs` environments for `ppo.num_steps`
    steps per cycle, so one actor batch is one learner update."""

    num_actors: int = 2
    """Actors `impulse launch` starts (on several machines: every actor of the run); at least 1."""
    credits: int = 1
    """Trajectory batches an actor may have in flight to the learner; bounds memory and policy lag. When the
    learner is the bottleneck every actor keeps its credits in use, so the lag is about num_actors x credits
    versions: keep that within ppo.max_policy_lag, or batches are dropped as stale."""
    when_no_credit: Literal["wait", "drop_oldest"] = "wait"
    """With no credit left: "wait" pauses the actor until the learner frees one; "drop_oldest" keeps rolling out
    and replaces its one held-back batch with the newer one (every replaced batch is counted as dropped)."""
    credit_timeout_s: float = 30.0
    """No acknowledgement from the learner for this long while out of credit: the batches in flight are taken
    as lost (a learner restarted without them) and the credits are reset. While the learner's recent pace says a
    batch may still be in its queue ((num_actors x credits + 1) of its updates), the actor waits that long instead."""
    memory_fraction: float = 0.0
    """Fraction of the GPU's memory each actor process preallocates (XLA_PYTHON_CLIENT_MEM_FRACTION), so several
    actors and the learner can share one GPU; 0 keeps JAX's default (75% for the first process)."""
    lockstep: bool = False
    """Actor and learner take turns: every batch is rolled out by the weights of the update just before it (policy
    lag 0), and the actor's random stream depends on the run's seed and its index only, not on its incarnation.
    With one actor and a fixed level set (`env.levels`), a launch then gives the same learner metrics for the same
    seed, bit for bit on one machine: for reproducing a run, and for checking that a change left the distributed
    mode's behaviour as it was. Needs num_actors = 1 and learner.publish_every = 1; slower, since each side waits
    while the other works. With the curriculum service the level batches still depend on when its results arrive."""
    devices: tuple[int, ...] = ()
    """GPUs the actors run on, as positions among the GPUs the process may see: actor i takes
    devices[i % len(devices)] and sees only it (CUDA_VISIBLE_DEVICES); empty: every actor sees them all and JAX
    uses the first."""

    def __post_init__(self) -> None:
        check_device_list("actors.devices", self.devices)
        check_range("actors.num_actors", self.num_actors, at_least=1)
        check_range("actors.credits", self.credits, at_least=1)
        check_range("actors.credit_timeout_s", self.credit_timeout_s, above=0)
        check_range("actors.memory_fraction", self.memory_fraction, at_least=0, below=1)
        if self.lockstep and self.num_actors != 1:
            raise ValueError(f"actors.lockstep takes turns with one actor, not {self.num_actors}: set "
                             "actors.num_actors=1")
