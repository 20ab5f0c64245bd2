"""Watching the PPO update for numbers that are not numbers, in both modes.

`learner.update.ppo_update` already refuses its own result when a NaN or an infinity appears in it (the update is
skipped, parameters and optimiser state kept, and its `non_finite` metric is 1). What the device cannot do is
decide when to give up and tell a person why: that is `NonFiniteGuard`, which the fused trainer and the learner
service feed with every update's metrics on the host. It counts the skipped updates over the run (the
`skipped/non_finite` column of metrics.jsonl and the status line), stops the run with `NonFiniteUpdates` after
`ppo.max_non_finite_updates` in a row (raised by `check` at the start of the service's next cycle, so that the
last update's metrics row is written first), naming the updates and the settings that usually cause it, and warns, at
most once every WARN_EVERY_UPDATES updates, while a finite loss has grown past DIVERGING_LOSS (a learning rate far
too large drives the loss to 1e14 and the entropy to 0 long before anything overflows).

And the last line of defence: `refuse_non_finite` is called before parameters are checkpointed, exported or
published, so that a non-finite tree never leaves the process that holds it, whatever produced it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from impulse.engine.pytree import count_non_finite
from impulse.learner.config import PPOConfig

log = logging.getLogger("impulse.learner")

SKIPPED_COLUMN = "skipped/non_finite"
"""metrics.jsonl column: updates skipped so far in the run because something in them was not finite."""
DIVERGING_LOSS = 1e4
"""A finite total loss above this (in absolute value) means training is diverging: PPO's losses on Kinetix's
rewards stay within a few units."""
WARN_EVERY_UPDATES = 100
"""While the loss stays above DIVERGING_LOSS, the warning is repeated at most this often."""


class NonFiniteUpdates(RuntimeError):
    """`ppo.max_non_finite_updates` updates in a row were skipped: the run cannot go on as configured."""


class NonFiniteParameters(RuntimeError):
    """Parameters about to be checkpointed, exported or published hold NaN or infinity."""


def likely_cause(ppo: PPOConfig) -> str:
    """What usually makes an update non-finite or divergent, with this run's values of those settings."""
    return (f"a learning rate or gradient-norm clip too large for this network "
            f"(ppo.learning_rate={ppo.learning_rate:g}, ppo.max_grad_norm={ppo.max_grad_norm:g})")


@dataclass
class NonFiniteGuard:
    """Counts skipped updates and decides when the run stops (see the module docstring). `skipped` is the run's
    total (a resumed run starts from its checkpoint's); `in_a_row` the current streak."""

    ppo: PPOConfig
    skipped: int = 0
    in_a_row: int = 0
    failure: NonFiniteUpdates | None = None
    """Set once the run must stop; `check` raises it."""
    _last_warning: int | None = None

    def check(self) -> None:
        """Raise `failure` if the run must stop (a service calls this first thing in every cycle)."""
        if self.failure is not None:
            raise self.failure

    def note(self, update: int, metrics: dict[str, float]) -> None:
        """After update number `update` (1-based, the run's count) with its host metrics: count it if it was
        skipped, and set `failure` once `ppo.max_non_finite_updates` were skipped in a row; warn if the loss is
        finite but diverging."""
        if metrics.get("non_finite", 0.0) > 0:
            self.skipped += 1
            self.in_a_row += 1
            log.warning("update %d skipped: its loss, gradients or parameters were not finite (NaN or infinity); "
                        "the parameters are kept as they were (%d in a row)", update, self.in_a_row)
            limit = self.ppo.max_non_finite_updates
            if limit and self.in_a_row >= limit:
                first = update - self.in_a_row + 1
                self.failure = NonFiniteUpdates(
                    f"updates {first} to {update}: {self.in_a_row} updates in a row were skipped because their "
                    f"loss, gradients or parameters were not finite, so the policy is still that of update "
                    f"{first - 1}; the likely cause is {likely_cause(self.ppo)}: lower them (or raise "
                    f"ppo.max_non_finite_updates to skip more in a row)")
            return
        self.in_a_row = 0
        loss = metrics.get("total_loss")
        if loss is None or not math.isfinite(loss) or abs(loss) <= DIVERGING_LOSS:
            return
        if self._last_warning is None or update - self._last_warning >= WARN_EVERY_UPDATES:
            self._last_warning = update
            log.warning("update %d: the loss is %.3g (above %g in size): training is diverging; the likely cause "
                        "is %s", update, loss, DIVERGING_LOSS, likely_cause(self.ppo))

    def columns(self) -> dict[str, float]:
        """The metrics.jsonl column this guard keeps."""
        return {SKIPPED_COLUMN: float(self.skipped)}


def refuse_non_finite(params: Any, what: str) -> None:
    """Raise `NonFiniteParameters` naming `what` (e.g. "checkpoint 120") and how many floats are bad, if `params`
    holds a NaN or an infinity anywhere."""
    bad, total = count_non_finite(params)
    if bad:
        raise NonFiniteParameters(f"refusing {what}: {bad:,} of {total:,} parameters are not finite (NaN or "
                                  "infinity)")
