"""Checkpoints with orbax: everything needed to continue a run bit for bit, written in the background.

A checkpoint holds one pytree (whatever the trainer carries between iterations: parameters, optimiser state,
environment state, random keys) plus JSON counters and the resolved config. Orbax writes each step into a
temporary directory and renames it when complete, so a process killed mid-write (kill -9) leaves the previous
checkpoints intact and the partial one is ignored and cleaned up on the next start.

Kept: the newest `keep_last` checkpoints and, when a metric is given, the best one by that metric.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp
from orbax.checkpoint.checkpoint_managers import preservation_policy

from learner.config import CheckpointConfig

BEST_METRIC = "solve_rate"


class CheckpointError(RuntimeError):
    """A checkpoint directory cannot be used (missing, empty, or from a run with a different structure)."""


class Checkpointer:
    """Asynchronous save and exact restore of a run's state under `directory`."""

    def __init__(self, directory: str | Path, config: CheckpointConfig | None = None):
        config = config or CheckpointConfig()
        self.directory = Path(directory).absolute()
        policies: list[Any] = [preservation_policy.LatestN(n=config.keep_last)]
        if config.keep_best:
            policies.append(
                preservation_policy.BestN(
                    get_metric_fn=lambda metrics: float(metrics[BEST_METRIC]),
                    n=1,
                    keep_checkpoints_without_metrics=False,
                )
            )
        options = ocp.CheckpointManagerOptions(
            preservation_policy=preservation_policy.AnyPreservationPolicy(policies),
            cleanup_tmp_directories=True,
            enable_async_checkpointing=True,
            create=True,
        )
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def save(
        self, step: int, state: Any, counters: dict[str, Any], config_toml: str, solve_rate: float | None = None
    ) -> None:
        """Start writing checkpoint `step` in the background (the arrays are copied off the device first)."""
        metrics = None if solve_rate is None else {BEST_METRIC: float(solve_rate)}
        self._manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(state),
                counters=ocp.args.JsonSave(counters),
                config=ocp.args.JsonSave({"toml": config_toml}),
            ),
            metrics=metrics,
        )

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self._manager.all_steps())

    def restore(self, template: Any, step: int | None = None) -> tuple[Any, dict[str, Any], str]:
        """(state, counters, config TOML) of checkpoint `step` (default: the newest), shaped like `template`."""
        step = self.latest_step() if step is None else step
        if step is None:
            raise CheckpointError(f"no complete checkpoint in {self.directory}")
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, template)
        try:
            restored = self._manager.restore(
                step,
                args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(abstract),
                    counters=ocp.args.JsonRestore(),
                    config=ocp.args.JsonRestore(),
                ),
            )
        except (ValueError, KeyError, FileNotFoundError) as err:
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} does not match this run's state "
                f"(different network, sizes or number of environments?): {err}"
            ) from err
        return restored["state"], dict(restored["counters"]), restored["config"]["toml"]

    def read_config(self, step: int | None = None) -> str:
        """The resolved config TOML saved with a checkpoint, without restoring its arrays."""
        step = self.latest_step() if step is None else step
        if step is None:
            raise CheckpointError(f"no complete checkpoint in {self.directory}")
        restored = self._manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))
        return restored["config"]["toml"]

    def wait(self) -> None:
        """Block until background writes are on disk."""
        self._manager.wait_until_finished()

    def close(self) -> None:
        self._manager.wait_until_finished()
        self._manager.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
