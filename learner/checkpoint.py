"""Checkpoints with orbax: everything needed to continue a run bit for bit, written in the background.

A checkpoint is a set of named items, so that each reader restores only what it needs:
- `train`: parameters, optimiser state and policy version (a pytree), with the JSON items `counters` (updates,
  env steps, the metrics window) and `config` (the resolved TOML) beside it. Every mode writes it; evaluation
  restores it alone, so `impulse eval` reads checkpoints of fused and distributed runs alike.
- `envs`: every environment's state and the random keys of a fused run (fused mode only).
- `curriculum`: a curriculum's buffer and knobs, when a run has one.
Orbax writes each step into a temporary directory and renames it when complete, so a process killed mid-write
(kill -9) leaves the previous checkpoints intact and the partial one is ignored and cleaned up on the next start.

A background write that fails (orbax raises its error at the next save or wait) costs that checkpoint alone: the
error is logged with its step, counted in `Checkpointer.failed_saves`, and the run goes on with the next save; the
checkpoints before it stay as they were.

A full disk (ENOSPC, EDQUOT, EIO; tensorstore says it as `RESOURCE_EXHAUSTED ... [os_error_code='28']`) is not
let pass that way: what orbax had written of the failed checkpoint (its `<step>.orbax-checkpoint-tmp` directory,
which it leaves behind and which holds the space) is removed, orbax forgets the step, and `save` (or `wait`,
`close`) raises `engine.io_errors.DiskFullError`, naming the checkpoint's path and the space left, so that the run
loop can wait for space and save again (`deploy.runtime.runloop`). The newest complete checkpoint stays the newest:
a restore, in this process or the next, never sees a partial one. While the disk is short of room (less than twice
a checkpoint's size free, or the last write failed for lack of it), `save` waits for its own write, so that its
failure is raised by that save (and the loop's last one is known to be on disk before the process ends) rather
than by the next. Orbax's own report of such a failure (an ERROR with a long traceback, into a log on the same full
disk) is left out: the one line of `DiskFullError` says it.

Kept: the newest `keep_last` checkpoints and, when a metric is given, the best one by that metric.

Verification on restore. Orbax itself only lists finalised steps (its temporary directories are ignored); it checks
neither that an item's files are complete nor, for plain arrays, that their shapes fit the reader's template. So
`Checkpointer.restore` checks each checkpoint it reads, in this order:
1. The item directories: the JSON items `counters` and `config` and every item the reader asks for must be there.
   An item that the checkpoint's own metadata lists but whose directory is gone is corruption; an item the
   checkpoint never had is a mismatch (it was written by another mode).
2. `counters` and `config` are read and parsed.
3. For each array item asked for, its tree metadata (structure, shapes, dtypes: orbax's `_METADATA` file and the
   arrays' zarr headers in the OCDBT database) is read and compared with the template.
4. The arrays are restored.
A failure to read files in steps 1, 2, 3 or 4 (truncated or garbled data or metadata, unparsable JSON, an item's
files missing) is *corruption*. Metadata that reads fine but describes another tree (other leaves, other shapes)
is a *mismatch*: the checkpoint is intact but belongs to another network, sizes or number of environments, and
`CheckpointError` is raised at once without touching anything (a wrong config must never push good checkpoints
aside). A different dtype is neither: orbax casts, as for an imported bfloat16 policy. Flipped bits inside array
data go unnoticed: orbax's format holds no checksums of the data.

Corrupt checkpoints. When the newest checkpoint is asked for (`step=None`, as every `--resume` does) and it is
corrupt, a warning names its step, the item and the error, its directory is moved (never deleted) to
`<checkpoint directory>-corrupt/<step>` (`<step>-2`, ... if that exists), and the next newest is tried, until one
restores; `Restored.step` says which. So a damaged newest checkpoint costs the updates since the one before, and
a restarted service never crashes on the same files twice. A process reading a run it does not own (`impulse
eval`, export, `--init-from`, a shipped agent loaded to play: `restore(..., set_aside=False)`) only skips a
corrupt checkpoint and leaves it where it is. If none restores, `CheckpointError` lists each step
tried, its item and the problem; they have all been moved aside, and a learner or `impulse train --resume`
started after that refuses to start over while they are there (`nothing_usable` says where they are), while the
curriculum service starts with an empty buffer and says so. A checkpoint asked for by step
(`impulse eval --checkpoint RUN/checkpoints/12`) is never moved: a corrupt one raises `CorruptCheckpointError`.
What to do with a moved checkpoint: nothing, to go on; to inspect it, restore it by step with a `Checkpointer` on
the `-corrupt` folder; delete the folder when it is no longer wanted.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import orbax.checkpoint as ocp
from orbax.checkpoint.checkpoint_managers import preservation_policy

from impulse.engine.io_errors import DiskFullError, check_space, disk_full_code, disk_full_error, disk_usage, writing
from impulse.learner.config import CheckpointConfig

log = logging.getLogger(__name__)

BEST_METRIC = "solve_rate"
TRAIN = "train"
ENVS = "envs"
CURRICULUM = "curriculum"
ARRAY_ITEMS = (TRAIN, ENVS, CURRICULUM)
COUNTERS = "counters"
CONFIG = "config"
JSON_ITEMS = (COUNTERS, CONFIG)
LEGACY_ITEM = "state"
CORRUPT_SUFFIX = "-corrupt"
WHOLE_STEP = "*"
"""`CorruptCheckpointError.item` when the checkpoint as a whole is damaged (no item in it at all)."""
ORBAX_TMP = ".orbax-checkpoint-tmp"
"""What orbax adds to the name of a checkpoint (and of its items) while it is being written."""
ROOM_MARGIN_BYTES = 1 << 20
"""Free space beyond twice a checkpoint's arrays under which a save waits for its write (metadata, JSON items)."""

READ_ERRORS = (ValueError, OSError, KeyError, EOFError)
"""What reading damaged checkpoint files raises: tensorstore's errors (`OUT_OF_RANGE`, `DATA_LOSS`, ...) and JSON
decoding errors are ValueErrors, a missing file is an OSError, an item orbax cannot find a KeyError. Orbax wraps a
failed read of a device array in a bare `Exception` whose cause is one of these, so the whole chain of causes is
searched (`_read_error`). Deliberately not RuntimeError: the runtime's own failures (out of device memory) say
nothing about the files."""

Templates = Mapping[str, Any] | Callable[[frozenset[str]], Mapping[str, Any]]
"""The items to restore and their shapes: a mapping from item name to template pytree, or a function that picks
that mapping from the array items a checkpoint holds (it is called again for each checkpoint tried)."""


class CheckpointError(RuntimeError):
    """A checkpoint directory cannot be used (missing, empty, corrupt, or from a run with a different structure)."""


class CorruptCheckpointError(CheckpointError):
    """Checkpoint `step`'s item `item` (`WHOLE_STEP`: the checkpoint as a whole) could not be read from `path`:
    its files are damaged or missing. `detail` says so in words (which item, which file, what went wrong)."""

    def __init__(self, message: str, step: int, item: str, path: Path, problem: str, detail: str):
        super().__init__(message)
        self.step = step
        self.item = item
        self.path = path
        self.problem = problem
        self.detail = detail


def _another_steps_file(err: OSError, step: int) -> bool:
    """Whether `err` names a file that belongs to a checkpoint other than `step` (a previous write's)."""
    name = os.fspath(err.filename) if err.filename is not None else ""
    return bool(name) and f"{os.sep}{step}{os.sep}" not in name and f"{os.sep}{step}." not in name


class Restored(NamedTuple):
    """What `Checkpointer.restore` read: the array items asked for, the counters, the config TOML, and the step
    they came from (older than the newest when newer ones were corrupt)."""

    items: dict[str, Any]
    counters: dict[str, Any]
    config_toml: str
    step: int


class Checkpointer:
    """Asynchronous save and verified restore of a run's state under `directory` (see the module docstring)."""

    def __init__(self, directory: str | Path, config: CheckpointConfig | None = None):
        config = config or CheckpointConfig()
        self.directory = Path(directory).absolute()
        self.corrupt_directory = self.directory.with_name(self.directory.name + CORRUPT_SUFFIX)
        policies: list[Any] = [preservation_policy.LatestN(n=config.keep_last)]
        if config.keep_best:
            policies.append(
                preservation_policy.BestN(
                    get_metric_fn=lambda metrics: float(metrics[BEST_METRIC]),
                    n=1,
                    keep_checkpoints_without_metrics=False,
                )
            )
        several_processes = jax.process_count() > 1
        if several_processes:
            self.directory.mkdir(parents=True, exist_ok=True)  # orbax creates it only for a group of one
        options = ocp.CheckpointManagerOptions(
            preservation_policy=preservation_policy.AnyPreservationPolicy(policies),
            cleanup_tmp_directories=True,
            enable_async_checkpointing=True,
            create=not several_processes,
            # A learner on several hosts (`learner.hosts`) checkpoints from its leader alone, host copies of the
            # state every process holds: orbax must not wait for the others at its barriers.
            multiprocessing_options=ocp.options.MultiprocessingOptions(primary_host=0, active_processes={0})
            if several_processes else ocp.options.MultiprocessingOptions(),
        )
        self._manager = ocp.CheckpointManager(self.directory, options=options)
        # Items are read with their handlers directly: the manager's composite restore of some items only warns
        # about every item left out, and a restore here reads one item at a time to name the one that fails.
        self._tree_reader = ocp.StandardCheckpointHandler()
        self._json_reader = ocp.JsonCheckpointHandler()
        self._reads_abandoned = False  # an array read failed during this restore (`_quiet_abandoned_reads`)
        self.failed_saves = 0  # background writes that failed (module docstring)
        self._writing: int | None = None  # the step being written in the background
        self._short_of_space = False  # the last write failed for lack of disk: saves wait for their writes

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
        to pytrees. Raises `DiskFullError` when the disk is full (this write's, or the previous background write's,
        found here): what was written of it is gone, the checkpoints before it are intact, and the same save can be
        made again (the module docstring)."""
        unknown = set(items) - set(ARRAY_ITEMS)
        if unknown or not items:
            raise ValueError(f"checkpoint items must be among {ARRAY_ITEMS}, got {sorted(items)}")
        metrics = None if solve_rate is None else {BEST_METRIC: float(solve_rate)}
        # Host copies, taken here at once: orbax's own copy of device arrays goes through its thread pool and
        # held a service's main thread for tens of milliseconds per save (a curriculum service's answers waited).
        host = jax.device_get(dict(items))
        args = ocp.args.Composite(
            **{name: ocp.args.StandardSave(tree) for name, tree in host.items()},
            counters=ocp.args.JsonSave(counters),
            config=ocp.args.JsonSave({"toml": config_toml}),
        )
        self.wait()  # the previous write: orbax would raise its failure from `save`, without saying which it was
        if self._short_of_space:
            self._remove_partial()
        nbytes = sum(getattr(leaf, "nbytes", 8) for leaf in jax.tree.leaves(host))
        usage = disk_usage(self.directory)
        careful = self._short_of_space or (usage is not None and usage.free < 2 * nbytes + ROOM_MARGIN_BYTES)
        try:
            with writing(self.directory / str(step)):
                check_space(self.directory, nbytes)  # the test hook (`engine.io_errors`); nothing otherwise
                try:
                    self._manager.save(step, args=args, metrics=metrics)
                except OSError as err:
                    if not _another_steps_file(err, step):
                        raise
                    # The previous write's metadata, finished by orbax after `wait` returned, failed (its folder
                    # went away): that write's failure, raised from this save; count it, then save this step.
                    self._failed_write(err, None)
                    self._manager.save(step, args=args, metrics=metrics)
        except DiskFullError as err:
            self.failed_saves += 1
            self._after_disk_full(err)
            raise
        self._writing = step
        if careful:
            self.wait()  # raises this write's DiskFullError, cleaned up after
            self._space_again()

    def _failed_write(self, err: Exception, step: int | None) -> None:
        """A background write failed: count it; for lack of disk, clean up after it and raise `DiskFullError`;
        otherwise log it (the run goes on with the next save)."""
        self.failed_saves += 1
        full = disk_full_error(self.directory if step is None else self.directory / str(step), err)
        if full is not None:
            _SHORT_OF_SPACE.add(id(self))  # before the failed write's other tasks report (`_hushed_reports`)
            time.sleep(ABANDONED_READ_GRACE_S)  # they may still be finishing: what they write is removed too
            self._after_disk_full(full)
            raise full from err
        log.error("a checkpoint failed to write in the background (%s: %s); the checkpoints before it are intact, "
                  "%d failed so far", type(err).__name__, err, self.failed_saves)

    def _after_disk_full(self, err: DiskFullError) -> None:
        """Remove what orbax wrote of checkpoints it did not finish and make it list the steps on disk again, so
        the failed step is neither the latest nor taken for saved; the next saves wait for their writes, and
        until one lands the failed writes' leftover reports are dropped (`_hushed_reports`)."""
        _SHORT_OF_SPACE.add(id(self))
        _install_hush()
        self._remove_partial(say=not self._short_of_space)  # said once, not at every retry
        self._manager.reload()
        self._short_of_space = True

    def _space_again(self) -> None:
        self._short_of_space = False
        _SHORT_OF_SPACE.discard(id(self))

    def _remove_partial(self, say: bool = False) -> None:
        """Remove orbax's temporary directories (checkpoints it did not finish: they hold space, and nothing reads
        them). Only when no write is under way; a late file of the failed write is removed by the next save."""
        for partial in sorted(self.directory.glob(f"*{ORBAX_TMP}*")):
            shutil.rmtree(partial, ignore_errors=True)
            if say:
                log.info("removed %s, what was written of a checkpoint the full disk cut short", partial)

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def set_aside(self) -> list[Path]:
        """The corrupt checkpoints moved out of this directory so far (by this process or an earlier one)."""
        if not self.corrupt_directory.is_dir():
            return []
        return sorted(self.corrupt_directory.iterdir())

    def nothing_usable(self) -> str:
        """Why there is no checkpoint to resume, for an error message: none was written, or every one was corrupt
        and set aside (named, so that a run never starts over silently)."""
        aside = self.set_aside()
        if not aside:
            return f"no complete checkpoint in {self.directory}"
        return (f"no usable checkpoint in {self.directory}: {len(aside)} corrupt one(s) were moved to "
                f"{self.corrupt_directory} ({', '.join(p.name for p in aside)}); to start the run over, move that "
                "folder away")

    def all_steps(self) -> list[int]:
        return list(self._manager.all_steps())

    def items_at(self, step: int | None = None) -> set[str]:
        """The array items (of `ARRAY_ITEMS`) checkpoint `step` (default: the newest) holds, from its directory
        listing (nothing is read, so a corrupt checkpoint answers too)."""
        self.wait()
        step = self._existing_step(step)
        return set(self._present(step)) & set(ARRAY_ITEMS)

    def restore(self, templates: Templates, step: int | None = None, set_aside: bool = True) -> Restored:
        """Checkpoint `step`, or by default the newest one that is intact: only the array items named in
        `templates` are read, each shaped like its template. Newer corrupt checkpoints are moved aside on the way
        (see the module docstring), or only skipped with `set_aside=False`: what a reader of a run it does not own
        passes (an evaluation, an export, a shipped agent loaded to play), so that it never moves another
        process's files. Raises `CheckpointError` if the checkpoint does not fit the templates or none is usable,
        `CorruptCheckpointError` if the explicitly asked `step` is corrupt."""
        self.wait()  # a save still being written is not on disk yet
        self._reads_abandoned = False
        with _quiet_abandoned_reads(lambda: self._reads_abandoned):
            return self._restore(templates, step, set_aside)

    def _restore(self, templates: Templates, step: int | None, set_aside: bool) -> Restored:
        if step is not None:
            self._existing_step(step)
            try:
                return self._restore_step(step, templates)
            except CorruptCheckpointError as err:
                raise CorruptCheckpointError(
                    f"{err} (left in place; steps in {self.directory}: {self._steps_text()})",
                    err.step, err.item, err.path, err.problem, err.detail,
                ) from err
        steps = sorted(self.all_steps(), reverse=True)
        if not steps:
            raise CheckpointError(f"no complete checkpoint in {self.directory}")
        failures: list[str] = []
        for candidate in steps:
            try:
                restored = self._restore_step(candidate, templates)
            except CorruptCheckpointError as err:
                fate = f"moved to {self._move_aside(candidate)}" if set_aside else "left in place"
                log.warning("checkpoint %d is corrupt: %s; %s, trying the next newest", candidate, err.detail, fate)
                failures.append(f"checkpoint {candidate}: {err.detail}; {fate}")
                continue
            if failures:
                kept = self.corrupt_directory if set_aside else self.directory
                log.warning("restored checkpoint %d: the %d newer one(s) were corrupt and are kept in %s", candidate,
                            len(failures), kept)
            return restored
        raise CheckpointError(f"no usable checkpoint in {self.directory}: every one is corrupt:\n  "
                              + "\n  ".join(failures))

    def wait(self) -> None:
        """Block until background writes are on disk, or have failed: logged and counted, and for lack of disk
        raised as `DiskFullError` once what was written of it is removed (the module docstring)."""
        step, self._writing = self._writing, None
        try:
            self._manager.wait_until_finished()
        except Exception as err:  # noqa: BLE001 - orbax raises a background write's failure here, once
            self._failed_write(err, step)

    def close(self) -> None:
        """Wait for the writes (raising `DiskFullError` if the last one did not fit), then release everything."""
        try:
            self.wait()
            self._space_again()
        finally:
            self._manager.close()
            self._tree_reader.close()
            self._json_reader.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- verification --------------------------------------------------------------------------------------------

    def _restore_step(self, step: int, templates: Templates) -> Restored:
        """Checkpoint `step`, checked in the order the module docstring gives. Raises `CorruptCheckpointError`
        for damaged files and `CheckpointError` for a checkpoint that is intact but does not fit `templates`."""
        present = self._present(step)
        saved = self._saved_items(step)
        written = present | saved
        if LEGACY_ITEM in written and not written & set(ARRAY_ITEMS):
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} was written by an older Impulse (one combined 'state' "
                "item, before checkpoints were split into train/envs items); it cannot be restored: start a new run"
            )
        if not written & set(ARRAY_ITEMS):
            raise self._corrupt(step, WHOLE_STEP, "it holds no items")
        # The items it was written with (not only those still there), so that a lost item is seen as corruption.
        chosen = dict(templates(frozenset(written & set(ARRAY_ITEMS))) if callable(templates) else templates)
        for name in (*JSON_ITEMS, *sorted(chosen)):
            if name not in present and (name in saved or name in JSON_ITEMS):
                raise self._corrupt(step, name, "its directory is missing")
        missing = set(chosen) - present
        if missing:
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} has no {', '.join(sorted(missing))} item "
                f"(it holds {', '.join(sorted(present & set(ARRAY_ITEMS)))}); was it written by another mode?"
            )
        counters = self._read_json(step, COUNTERS)
        config_toml = self._read_json(step, CONFIG)["toml"]
        abstract = {name: jax.tree.map(_placed_here, tree) for name, tree in chosen.items()}
        for name, tree in abstract.items():
            self._check_tree(step, name, tree)
        items = {}
        for name, tree in abstract.items():
            try:
                items[name] = self._tree_reader.restore(
                    self.directory / str(step) / name, args=ocp.args.StandardRestore(tree)
                )
            except Exception as err:
                self._reads_abandoned = True
                cause = _read_error(err)
                if cause is None:
                    raise
                raise self._corrupt(step, name, _describe(cause)) from err
        return Restored(items, counters, config_toml, step)

    def _read_json(self, step: int, name: str) -> dict[str, Any]:
        """JSON item `name` (`counters` or `config`) of checkpoint `step`; raises `CorruptCheckpointError` if it
        fails to read or parse, or parses to something else than what `save` writes."""
        try:
            value = self._json_reader.restore(self.directory / str(step) / name, args=ocp.args.JsonRestore())
        except Exception as err:  # reading a file, parsing JSON: any failure is the file's
            raise self._corrupt(step, name, _describe(err)) from err
        if not isinstance(value, dict):
            raise self._corrupt(step, name, f"holds {type(value).__name__}, not a JSON object")
        if name == CONFIG and not isinstance(value.get("toml"), str):
            raise self._corrupt(step, name, "holds no 'toml' text")
        return dict(value)

    def _check_tree(self, step: int, name: str, template: Any) -> None:
        """Compare item `name`'s saved tree metadata with `template`: unreadable is corruption; other leaves or
        shapes are a mismatch (CheckpointError). Dtypes may differ: orbax casts on restore."""
        try:
            saved = ocp.tree.to_flat_dict(self._tree_reader.metadata(self.directory / str(step) / name).tree)
        except Exception as err:  # files alone are read here (no template, no device)
            raise self._corrupt(step, name, f"its metadata cannot be read: {_describe(err)}") from err
        wanted = ocp.tree.to_flat_dict(template)
        differences = [f"{_path(key)} only in the checkpoint" for key in saved.keys() - wanted.keys()]
        differences += [f"{_path(key)} only in this run" for key in wanted.keys() - saved.keys()]
        for key in saved.keys() & wanted.keys():
            shapes = (getattr(saved[key], "shape", None), getattr(wanted[key], "shape", None))
            if None not in shapes and tuple(shapes[0]) != tuple(shapes[1]):
                differences.append(f"{_path(key)} is {tuple(shapes[0])} in the checkpoint, {tuple(shapes[1])} here")
        if differences:
            shown = "; ".join(sorted(differences)[:6]) + (f"; and {len(differences) - 6} more"
                                                          if len(differences) > 6 else "")
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} does not match this run's state "
                f"(different network, sizes or number of environments?): {name}: {shown}"
            )

    # -- helpers -------------------------------------------------------------------------------------------------

    def _existing_step(self, step: int | None) -> int:
        """`step`, or the newest, checked to be a checkpoint in the directory."""
        if step is None:
            step = self.latest_step()
            if step is None:
                raise CheckpointError(f"no complete checkpoint in {self.directory}")
        elif not (self.directory / str(step)).is_dir():  # orbax renames a step into place once it is complete
            raise CheckpointError(f"no checkpoint {step} in {self.directory} (it holds: {self._steps_text()})")
        return step

    def _present(self, step: int) -> set[str]:
        """The item directories of checkpoint `step`."""
        try:
            return {p.name for p in (self.directory / str(step)).iterdir() if p.is_dir()}
        except OSError as err:
            raise CheckpointError(f"checkpoint {step} in {self.directory} cannot be listed: {err}") from err

    def _saved_items(self, step: int) -> set[str]:
        """The items that checkpoint `step`'s own metadata says were written (empty if it cannot be read: then
        orbax guesses from the directories and a missing item counts as never written)."""
        try:
            return set(ocp.metadata.get_step_metadata(self.directory / str(step)).item_handlers or {})
        except (*READ_ERRORS, TypeError, AttributeError):
            return set()

    def _corrupt(self, step: int, item: str, problem: str) -> CorruptCheckpointError:
        if item == WHOLE_STEP:
            path = self.directory / str(step)
            detail = f"its directory ({path}) cannot be used: {problem}"
        else:
            path = self.directory / str(step) / item
            if item in JSON_ITEMS:
                path = path / "metadata"  # the one file a JSON item is written to
            detail = f"its {item} item ({path}) cannot be read: {problem}"
        return CorruptCheckpointError(f"checkpoint {step} in {self.directory} is corrupt: {detail}",
                                      step, item, path, problem, detail)

    def _move_aside(self, step: int) -> Path:
        """Move checkpoint `step` into the `-corrupt` sibling folder (keeping all its files) and make the manager
        forget it, so that the next newest becomes the latest and the step number can be written again."""
        self.corrupt_directory.mkdir(parents=True, exist_ok=True)
        target = self.corrupt_directory / str(step)
        suffix = 1
        while target.exists():
            suffix += 1
            target = self.corrupt_directory / f"{step}-{suffix}"
        try:
            shutil.move(self.directory / str(step), target)
        except OSError as err:
            raise CheckpointError(
                f"checkpoint {step} in {self.directory} is corrupt and could not be moved to {target}: {err}; "
                "move it out of the directory by hand"
            ) from err
        self._manager.reload()
        return target

    def _steps_text(self) -> str:
        return ", ".join(str(s) for s in self.all_steps()) or "none"


ABANDONED_READ_GRACE_S = 0.2
"""How long the reads orbax abandoned are given to finish (and report) before their reports are let through."""


FINE_TUNING_COUNTERS = ("init_from", "init_from_step", "init_from_env_steps")
"""The counters by which a fine-tuning run's checkpoints say where its starting policy came from."""


class StartingPolicy(NamedTuple):
    """A fine-tuning run's start: the parameters of another run's checkpoint and `origin`, the
    `FINE_TUNING_COUNTERS` that the new run writes into each of its checkpoints."""

    params: Any
    origin: dict[str, Any]


def read_starting_policy(source: Path, train_template: Any, config: CheckpointConfig) -> StartingPolicy:
    """The policy parameters of `source`'s newest intact checkpoint (a run directory of either mode, or a shipped
    agent such as pretrained/general-s), for `--init-from`. `train_template`: a `train` item of the new run's
    network. The source is read as a reader reads it: a corrupt checkpoint there is skipped, never moved. Raises
    `CheckpointError` (none usable, or another network)."""
    with Checkpointer(source / config.directory, config) as checkpoints:
        restored = checkpoints.restore({TRAIN: train_template}, set_aside=False)
    origin = {"init_from": str(source), "init_from_step": restored.step,
              "init_from_env_steps": int(restored.counters.get("env_steps", 0))}
    log.info("fine-tuning the policy of %s (checkpoint %d, trained for %s env steps)", source, restored.step,
             f"{origin['init_from_env_steps']:,}")
    return StartingPolicy(restored.items[TRAIN].params, origin)


def fine_tuning_origin(counters: Mapping[str, Any]) -> dict[str, Any]:
    """The `FINE_TUNING_COUNTERS` among a restored checkpoint's counters, so that a resumed fine-tuning run keeps
    saying where it started."""
    return {key: counters[key] for key in FINE_TUNING_COUNTERS if key in counters}


@contextlib.contextmanager
def _quiet_abandoned_reads(abandoned: Callable[[], bool]) -> Iterator[None]:
    """When one read of an item fails, orbax abandons the item's other reads and each of them later reports an
    'Exception ignored' traceback (a closed event loop, a discarded coroutine): thousands of lines in a service's
    log for one corrupt checkpoint, already described by one warning. While this is open those reports are
    dropped and every other one goes on to the previous hook; on the way out, if reads were `abandoned()`, they
    are given a moment to finish and are collected."""
    previous = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        if not _is_abandoned_read(unraisable):
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        if abandoned():
            time.sleep(ABANDONED_READ_GRACE_S)
            gc.collect()
        if sys.unraisablehook is hook:
            sys.unraisablehook = previous


def _is_abandoned_read(unraisable: Any) -> bool:
    error = unraisable.exc_value
    if isinstance(error, RuntimeError) and str(error) == "Event loop is closed":
        return True  # a tensorstore read completing after orbax closed its event loop
    return (getattr(unraisable.object, "__qualname__", "") == "_read_array_index_and_device_put"
            or _is_failed_array_read(error))


def _is_failed_array_read(error: BaseException | None) -> bool:
    """Orbax's wrapper around one failed read of a device array's index (its message is all that tells it)."""
    return error is not None and str(error).startswith("Encountered error while reading array index")


class _AbandonedReadTaskFilter(logging.Filter):
    """Drops asyncio's 'Task exception was never retrieved' report (an error with a traceback) for an abandoned
    array read: the task of a read orbax gave up on is collected whenever the garbage collector gets to it, so this
    can come after `_quiet_abandoned_reads` has closed, and the corrupt checkpoint has already been described by
    one warning. Every other asyncio record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        return not (_is_failed_array_read(error) and "never retrieved" in str(record.msg))


class _DiskFullReportFilter(logging.Filter):
    """Drops orbax's own reports of a write that failed for lack of disk (ERRORs on the `absl` logger, each with
    a traceback of some fifty lines, into a log that is likely on the same full disk): `Checkpointer` raises
    `DiskFullError` for it, whose one line says which checkpoint and how much space is left. Every other record
    passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.ERROR:
            return True
        error = record.exc_info[1] if record.exc_info else None
        return disk_full_code(error) is None and disk_full_code(Exception(record.getMessage())) is None


def _install_log_filters() -> None:
    """Attach `_AbandonedReadTaskFilter` to the `asyncio` logger, and `_DiskFullReportFilter` to it and to `absl`
    (orbax's: a write's tasks that failed for lack of disk report there as 'never retrieved'), once per process."""
    for name, kind in (("asyncio", _AbandonedReadTaskFilter), ("asyncio", _DiskFullReportFilter),
                       ("absl", _DiskFullReportFilter)):
        logger = logging.getLogger(name)
        if not any(isinstance(f, kind) for f in logger.filters):
            logger.addFilter(kind())


_SHORT_OF_SPACE: set[int] = set()
"""The checkpointers whose last write failed for lack of disk and none has landed since (`_hushed_reports`)."""


def _hushed_reports(previous: Callable[[Any], None]) -> Callable[[Any], None]:
    """`sys.unraisablehook` for the reports that orbax's abandoned work leaves: when a write fails (for lack of
    disk, at every retry), its other tasks complete after orbax closed their event loop, and each is reported,
    seconds later, as a traceback of 'Event loop is closed' (dozens per failure, into a log on the same full disk;
    the failure itself is said by orbax's exception, `DiskFullError`'s one line here). Those reports are always
    dropped; while a checkpointer is short of space, the other reports of abandoned work
    (`_is_abandoned_read`) too. Everything else goes on to `previous`."""

    def hook(unraisable: Any) -> None:
        if _is_closed_loop_report(unraisable) or (_SHORT_OF_SPACE and _is_abandoned_read(unraisable)):
            return
        previous(unraisable)

    hook.hushes = True  # type: ignore[attr-defined]
    return hook


def _is_closed_loop_report(unraisable: Any) -> bool:
    error = unraisable.exc_value
    return isinstance(error, RuntimeError) and str(error) == "Event loop is closed"


def _install_hush() -> None:
    """Put `_hushed_reports` in front of the current `sys.unraisablehook`, once."""
    if not getattr(sys.unraisablehook, "hushes", False):
        sys.unraisablehook = _hushed_reports(sys.unraisablehook)


_install_log_filters()
_install_hush()


def _read_error(err: BaseException) -> BaseException | None:
    """The first of `err` and its causes (`raise ... from`, or raised while handling) that is a `READ_ERRORS`."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        if isinstance(current, READ_ERRORS):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def _describe(err: BaseException) -> str:
    """One line of an error from orbax or tensorstore, without tensorstore's long spec dump."""
    text = str(err).split(" [tensorstore_spec=")[0].replace("\n", " ").strip() or type(err).__name__
    return text if len(text) <= 300 else text[:297] + "..."


def _path(key: tuple[str, ...]) -> str:
    return "/".join(str(part) for part in key)


def _placed_here(leaf: Any) -> Any:
    """The shape, dtype and placement a template leaf asks for, placed on this process's first device when the
    template names no placement: orbax would otherwise lay arrays out as the writer's devices were (a checkpoint
    written on a GPU then fails to read on a CPU with a topology mismatch)."""
    struct = ocp.utils.to_shape_dtype_struct(leaf)
    if getattr(struct, "sharding", None) is not None or not hasattr(struct, "shape"):
        return struct
    here = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    return jax.ShapeDtypeStruct(struct.shape, struct.dtype, sharding=here)

