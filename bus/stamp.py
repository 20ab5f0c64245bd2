"""What every frame a process sends says about the process: its run, the learner epoch and policy version it
acts for, and a sequence number per message kind. The `Bus` holds one `Stamp`; the process moves it forward (the
learner after each update, an actor when it adopts weights), and the message families (`bus.trajectories`,
`bus.weights`, ...) read it, so that a call site says only what it sends."""

from __future__ import annotations

from dataclasses import dataclass, field

from impulse.bus.codec import Kind


@dataclass
class Stamp:
    """The header fields a process puts on what it sends (see the module docstring)."""

    run: str
    epoch: int = 0
    """The learner's epoch: the learner's own, or that of the weights an actor acts with."""
    policy_version: int = 0
    """The learner's policy version, or that of the weights an actor acts with."""
    nonce: str = ""
    """The learner process's instance nonce (`bus.keys.INSTANCE`), which its weights frames carry; "" elsewhere."""
    _sequences: dict[Kind, int] = field(default_factory=dict, repr=False)

    def acting_for(self, epoch: int, policy_version: int) -> None:
        """From now on, frames say they come from (or act for) this epoch and policy version."""
        self.epoch, self.policy_version = epoch, policy_version

    def next_seq(self, kind: Kind) -> int:
        """1, 2, 3, ... for each kind of message this process sends (gaps mean loss to the receiver)."""
        self._sequences[kind] = self._sequences.get(kind, 0) + 1
        return self._sequences[kind]
