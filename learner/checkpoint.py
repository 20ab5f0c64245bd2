"""Checkpoints with orbax: everything needed to continue a run bit for bit, written in the background.

A checkpoint is a set of named items, so that each reader restores only what it needs:
- `train`: parameters, optimiser state and policy version (a pytree), with the JSON items `counters` (updates,
  env steps, the metrics window) and `config` (the resolved TOML) beside it. Every mode writes it; evaluation
  restores it alone, so `impulse eval` reads checkpoints of fused and distributed runs alike.
- `envs`: every environment's state and the random keys of a fused run (fused mode only).
- `curriculum`: a curriculum's buffer and knobs, when a run has one.
Orbax writes each step into a temporary directory and renames it when complete, so a process killed mid-write
(kill -9) leaves the previous checkpoints intact and the partial one is ignored and cleaned up on the next start.

Kept: the newest `keep_last` checkpoints and, when a metric is given, the best one by that metric.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp
from orbax.checkpoint.checkpoint_managers import preservation_policy

from learner.config import CheckpointConfig

BEST_METRIC = "solve_rate"
TRAIN = "train"
ENVS = "envs"
CURRICULUM = "curriculum"
ARRAY_ITEMS = (TRAIN, ENVS, CURRICULUM)


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
        self,
        step: int,
        items: Mapping[str, Any],
        counters: dict[str, Any],
        config_toml: str,
        solve_rate: float | None = None,
    ) -> None:
        """Start writing checkpoint `step` in the background (the arrays are copied off the device first).
        `items` maps item names (`ARRAY_ITEMS`: `train` for trainers, `curriculum` alone for the curriculum service)
        to pytrees."""
        unknown = set(items) - set(ARRAY_ITEMS)
        if unknown or not items:
            raise ValueError(f"checkpoint items must be among {ARRAY_ITEMS}, got {sorted(items)}")
        metrics = None if solve_rate is None else {BEST_METRIC: float(solve_rate)}
        self._manager.save(
            step,
            args=ocp.args.Composite(
                **{name: ocp.args.StandardSave(tree) for name, tree in items.items()},
                counters=ocp.args.JsonSave(counters),
                config=ocp.args.JsonSave({"toml": config_toml}),
            ),
            metrics=metrics,
        )

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self._manager.all_steps())

    def items_at(self, step: int | None = None) -> set[str]:
        """The array items (of `ARRAY_ITEMS`) checkpoint `step` (default: the newest) holds."""
        self.wait()
        step = self.latest_step() if step is None else step
        if step is None:
            raise CheckpointError(f"no complete checkpoint in {self.directory}")
        return {p.name for p in (self.directory / str(step)).iterdir() if p.is_dir()} & set(ARRAY_ITEMS)

    def restore(
        self, templates: Mapping[str, Any], step: int | None = None
    ) -> tuple[dict[str, Any], dict[str, Any], str]:
        """(items, counters, config TOML) of checkpoint `step` (default: the newest). Only the items named in
        `templates` are read, each shaped like its template."""
        self.wait()  # a save still being written is not on disk yet
        step = self.latest_step() if step is None else step
        if step is None:
            raise CheckpointError(f"no complete checkpoint in {self.directory}")
        present = {p.name for p in (self.directory / str(step)).iterdir() if p.is_dir()}
        if not present & set(ARRAY_ITEMS):
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} was written by an older Impulse (one combined 'state' "
                "item, before checkpoints were split into train/envs items); it cannot be restored: start a new run"
            )
        missing = set(templates) - present
        if missing:
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} has no {', '.join(sorted(missing))} item "
                f"(it holds {', '.join(sorted(present & set(ARRAY_ITEMS)))}); was it written by another mode?"
            )
        abstract = {name: jax.tree.map(ocp.utils.to_shape_dtype_struct, t) for name, t in templates.items()}
        try:
            restored = self._manager.restore(
                step,
                args=ocp.args.Composite(
                    **{name: ocp.args.StandardRestore(tree) for name, tree in abstract.items()},
                    counters=ocp.args.JsonRestore(),
                    config=ocp.args.JsonRestore(),
                ),
            )
        except (ValueError, KeyError, FileNotFoundError) as err:
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} does not match this run's state "
                f"(different network, sizes or number of environments?): {err}"
            ) from err
        items = {name: restored[name] for name in templates}
        return items, dict(restored["counters"]), restored["config"]["toml"]

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
