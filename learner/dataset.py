"""The recorded dataset: whole episodes the actors played, with the levels they played them on, in a zarr
hierarchy on disk (written by the recorder process, `learner.recorder`; read by behaviour cloning,
`learner.bc`, and by anyone with a zarr reader).

Layout (zarr format 3; every array is zstd-compressed and chunked along its first axis):

    <path>/zarr.json                         the root group; its attributes say `format`, `version`, the run's `env`
                                             section (the observation, action and size every episode shares) and
                                             the `network` section it was recorded with
    <path>/shards/<8-digit number>/          one shard: a group of whole episodes
        steps/obs/...     [S, ...]           the observation each action was chosen from (named as on the wire)
        steps/action      [S, ...]           the action taken
        steps/reward      [S]
        episodes/start    [N] int64          the episode's first step in `steps`
        episodes/length   [N] int32
        episodes/level_id [N] uint64         the level played (`engine.levels.level`'s 64-bit id)
        episodes/return   [N] float32        the episode's return
        episodes/solved   [N] bool           it ended with green touching blue
        episodes/policy_version [N] int32    the policy version that acted on its last step
        episodes/actor    [N] int32          the actor index that played it
        episodes/has_level [N] bool          its level is in `levels/` (the recorder heard it)
        levels/...        [K, ...]           each level the shard's episodes played, once (`Level`'s leaves)

The index of the dataset (level id, policy version, return and outcome of every episode) is the union of the
shards' small `episodes/` arrays (`Dataset.index`).

Safe against a kill at any moment: a shard is written whole under `<path>/.partial/` and then renamed into
`shards/` (a rename within one file system is atomic), so `shards/` holds complete shards only; what a killed
writer left in `.partial/` is removed when the dataset is opened for writing again, and numbering goes on after
the highest shard. Disk use is bounded (`DatasetWriter`'s `max_bytes`): when the next shard would pass it, the
writer either stops recording or deletes the oldest shards.

A full disk (`engine.io_errors.DiskFullError`: ENOSPC, EDQUOT, EIO) is not the dataset's limit but the file
system's: the shard it cut short is removed from `.partial/`, the writer says once, in one line, what failed and
how much space is left, keeps the episodes in memory (up to HELD_WHILE_FULL_BYTES; older ones are dropped and
counted in `episodes_dropped_disk_full`) and tries the shard again every RETRY_FULL_S seconds, reminding every
REMIND_FULL_S; once a shard fits, recording goes on where it was. Episodes still held when the writer's last flush
(`flush(final=True)`) fails are lost, and said so.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import shutil
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from impulse.engine.io_errors import DiskFullError, check_space, size_text, writing
from impulse.engine.levels.level import level_id_values

log = logging.getLogger(__name__)

DATASET_FORMAT = "impulse-episodes"
DATASET_VERSION = 1
SHARDS = "shards"
PARTIAL = ".partial"
SHARD_NAME = re.compile(r"^\d{8}$")
STEPS, EPISODES, LEVELS = "steps", "episodes", "levels"
CHUNK_ROWS = 4096
"""Rows per zarr chunk along the first axis."""
METADATA_BYTES = 1024
"""What a shard's size estimate adds per array and group for zarr's metadata (a zarr.json of about 700 bytes)."""
HELD_WHILE_FULL_BYTES = 256 * 2**20
"""While the disk is full, the episodes' bytes a writer keeps for the shard it writes once there is space."""
RETRY_FULL_S = 10.0
"""While the disk is full, how often a flush tries the shard again."""
REMIND_FULL_S = 60.0
"""While the disk is full, how often the writer says that it is still waiting."""


class DatasetError(ValueError):
    """A folder that is not a dataset of ours, one of another environment, or a shard that cannot be read."""


class Episode(NamedTuple):
    """One whole episode, on the host. `steps` maps names (`obs/...`, `action`, `reward`) to [L, ...] arrays;
    `level` is the level's leaves (unbatched, named as `engine.pytree.tree_arrays` names them) or None when the
    recorder never heard it."""

    steps: dict[str, np.ndarray]
    level_id: int
    episode_return: float
    solved: bool
    policy_version: int
    actor: int
    level: dict[str, np.ndarray] | None

    @property
    def length(self) -> int:
        return int(self.steps["reward"].shape[0])

    @property
    def nbytes(self) -> int:
        """The bytes of its arrays (steps and level)."""
        level = self.level.values() if self.level is not None else ()
        return sum(int(array.nbytes) for array in (*self.steps.values(), *level))


class EpisodeIndex(NamedTuple):
    """One row per episode of a dataset, in shard order (all [N])."""

    shard: np.ndarray  # int32: position of the shard in `Dataset.shards`
    start: np.ndarray  # int64: first step within the shard
    length: np.ndarray  # int32
    level_id: np.ndarray  # uint64
    episode_return: np.ndarray  # float32
    solved: np.ndarray  # bool
    policy_version: np.ndarray  # int32
    actor: np.ndarray  # int32
    has_level: np.ndarray  # bool

    @property
    def episodes(self) -> int:
        return int(self.length.shape[0])

    @property
    def steps(self) -> int:
        return int(self.length.sum())


_INDEX_ARRAYS = {"start": np.int64, "length": np.int32, "level_id": np.uint64, "return": np.float32,
                 "solved": np.bool_, "policy_version": np.int32, "actor": np.int32, "has_level": np.bool_}


def _zarr() -> Any:
    import zarr  # imported when a dataset is opened: most processes never touch one

    return zarr


def folder_bytes(path: Path) -> int:
    """Bytes of the files under `path`."""
    return sum(entry.stat().st_size for entry in path.rglob("*") if entry.is_file())


def _shard_folders(root: Path) -> list[Path]:
    shards = root / SHARDS
    if not shards.is_dir():
        return []
    return sorted(entry for entry in shards.iterdir() if entry.is_dir() and SHARD_NAME.match(entry.name))


def _write_arrays(group: Any, prefix: str, arrays: Mapping[str, np.ndarray]) -> None:
    for name, array in arrays.items():
        chunks = (max(1, min(CHUNK_ROWS, array.shape[0])), *array.shape[1:]) if array.ndim else ()
        group.create_array(f"{prefix}/{name}", data=np.ascontiguousarray(array), chunks=chunks)


def _read_arrays(group: Any, prefix: str) -> dict[str, np.ndarray]:
    """Every array under `prefix` of `group`, by its name below the prefix."""
    if prefix not in group:
        return {}
    top = group[prefix]
    return {name: np.asarray(array[...]) for name, array in top.arrays()} | {
        f"{name}/{inner}": values for name, _ in top.groups()
        for inner, values in _read_arrays(top, name).items()}


class Dataset:
    """A dataset opened for reading (see the module docstring); `open_dataset` makes one."""

    def __init__(self, path: Path, attrs: dict[str, Any], shards: list[Path]):
        self.path = path
        self.attrs = attrs
        self.shards = shards

    @property
    def env(self) -> dict[str, Any]:
        """The `[env]` section the episodes were recorded with."""
        return dict(self.attrs.get("env", {}))

    @property
    def network(self) -> dict[str, Any]:
        """The `[network]` section of the run that recorded it (what acted)."""
        return dict(self.attrs.get("network", {}))

    def _shard(self, position: int) -> Any:
        try:
            return _zarr().open_group(self.shards[position], mode="r")
        except Exception as err:  # zarr raises several kinds for unreadable metadata
            raise DatasetError(f"{self.shards[position]}: not a readable shard ({err})") from err

    def index(self) -> EpisodeIndex:
        """Every episode's row (see `EpisodeIndex`)."""
        columns: dict[str, list[np.ndarray]] = {name: [] for name in ("shard", *_INDEX_ARRAYS)}
        for position in range(len(self.shards)):
            group = self._shard(position)
            try:
                table = {name: np.asarray(group[f"{EPISODES}/{name}"][...], dtype) for name, dtype
                         in _INDEX_ARRAYS.items()}
            except Exception as err:
                raise DatasetError(f"{self.shards[position]}: its episode table cannot be read ({err})") from err
            columns["shard"].append(np.full(table["start"].shape, position, np.int32))
            for name, values in table.items():
                columns[name].append(values)
        joined = {name: np.concatenate(parts) if parts else np.zeros(0, _INDEX_ARRAYS.get(name, np.int32))
                  for name, parts in columns.items()}
        return EpisodeIndex(joined["shard"], joined["start"], joined["length"], joined["level_id"],
                            joined["return"], joined["solved"], joined["policy_version"], joined["actor"],
                            joined["has_level"])

    def steps(self, selected: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The steps (`obs/...`, `action`, `reward`) of the episodes `selected` (a bool mask over `index()`'s
        rows; all when None), concatenated in index order."""
        index = self.index()
        if selected is None:
            selected = np.ones(index.episodes, bool)
        parts: dict[str, list[np.ndarray]] = {}
        for position in range(len(self.shards)):
            rows = np.flatnonzero(selected & (index.shard == position))
            if not rows.size:
                continue
            arrays = _read_arrays(self._shard(position), STEPS)
            take = np.concatenate([np.arange(index.start[r], index.start[r] + index.length[r]) for r in rows])
            for name, array in arrays.items():
                parts.setdefault(name, []).append(array[take])
        return {name: np.concatenate(chunks) for name, chunks in parts.items()}

    def levels(self) -> dict[int, dict[str, np.ndarray]]:
        """Every recorded level by id: its leaves, unbatched, named as `engine.pytree.tree_arrays` names them."""
        found: dict[int, dict[str, np.ndarray]] = {}
        for position in range(len(self.shards)):
            arrays = _read_arrays(self._shard(position), LEVELS)
            if not arrays:
                continue
            ids = level_id_values(arrays["level_id"])
            for row, level_id in enumerate(ids):
                found.setdefault(int(level_id), {name: array[row] for name, array in arrays.items()})
        return found


def _read_attrs(path: Path) -> dict[str, Any]:
    try:
        attrs = dict(_zarr().open_group(path, mode="r").attrs)
    except Exception as err:
        raise DatasetError(f"{path}: not a zarr group ({err})") from err
    if attrs.get("format") != DATASET_FORMAT:
        raise DatasetError(f"{path}: a zarr group, but not an Impulse episode dataset (its format attribute is "
                           f"{attrs.get('format')!r}, expected {DATASET_FORMAT!r})")
    if attrs.get("version") != DATASET_VERSION:
        raise DatasetError(f"{path}: dataset version {attrs.get('version')!r}, this Impulse reads version "
                           f"{DATASET_VERSION}")
    return attrs


def open_dataset(path: str | Path) -> Dataset:
    """Open a recorded dataset for reading; `DatasetError` names the problem if `path` is not one."""
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"{path}: no such folder")
    return Dataset(path, _read_attrs(path), _shard_folders(path))


def _plain(value: Any) -> Any:
    """A config section as JSON-able values (tuples as lists)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [_plain(item) for item in value]
    return value


WhenFull = Literal["stop", "drop_oldest"]


class DatasetWriter:
    """Appends whole episodes to a dataset in shards (see the module docstring). Episodes wait in memory until
    `flush` writes them as one shard."""

    def __init__(self, path: str | Path, env: Any, network: Any, *, max_bytes: int,
                 when_full: WhenFull = "stop"):
        """`env`, `network`: the run's sections (dataclasses or dicts), kept in the root's attributes; an existing
        dataset must have been recorded with the same `env` section."""
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.when_full = when_full
        env, network = _plain(env), _plain(network)
        zarr = _zarr()
        if (self.path / "zarr.json").is_file():
            attrs = _read_attrs(self.path)
            if attrs.get("env") != env:
                raise DatasetError(f"{self.path} was recorded with env {attrs.get('env')}, not this run's {env}; "
                                   "record into another folder")
        else:
            with writing(self.path):
                self.path.mkdir(parents=True, exist_ok=True)
                root = zarr.open_group(self.path, mode="w")
                root.attrs.update({"format": DATASET_FORMAT, "version": DATASET_VERSION, "env": env,
                                   "network": network, "created": time.time()})
                root.create_group(SHARDS)
        partial = self.path / PARTIAL
        if partial.exists():
            left = sorted(entry.name for entry in partial.iterdir())
            if left:
                log.info("removing %d shard(s) a killed recorder left unfinished in %s", len(left), partial)
            shutil.rmtree(partial)
        shards = _shard_folders(self.path)
        self.next_shard = int(shards[-1].name) + 1 if shards else 0
        self.bytes_used = folder_bytes(self.path)
        self.pending: list[Episode] = []
        self.full = False
        self.counts = {"episodes_written": 0, "steps_written": 0, "shards_written": 0, "shards_dropped": 0,
                       "episodes_dropped_full": 0, "episodes_dropped_disk_full": 0}
        self.last_flush = time.monotonic()
        self.disk_full: DiskFullError | None = None
        """Why the last shard could not be written for lack of disk (None once one is)."""
        self._retry_at = self._remind_at = 0.0

    @property
    def pending_steps(self) -> int:
        return sum(episode.length for episode in self.pending)

    def add(self, episodes: Iterable[Episode]) -> None:
        """Keep whole episodes for the next shard (or count them as dropped when the dataset is full)."""
        for episode in episodes:
            if self.full:
                self.counts["episodes_dropped_full"] += 1
            else:
                self.pending.append(episode)

    def flush(self, final: bool = False) -> Path | None:
        """Write the waiting episodes as one shard; returns its folder (None when nothing was written). While the
        disk is full (the module docstring) the episodes stay waiting and the shard is tried at most every
        RETRY_FULL_S; `final` (the writer's last flush) tries it at once, and what it cannot write is lost."""
        now = self.last_flush = time.monotonic()
        episodes = self.pending
        if not episodes:
            return None
        if self.disk_full is not None and not final and now < self._retry_at:
            return None
        steps = {name: np.concatenate([episode.steps[name] for episode in episodes]) for name in episodes[0].steps}
        lengths = np.asarray([episode.length for episode in episodes], np.int32)
        table = {
            "start": np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64),
            "length": lengths,
            "level_id": np.asarray([episode.level_id for episode in episodes], np.uint64),
            "return": np.asarray([episode.episode_return for episode in episodes], np.float32),
            "solved": np.asarray([episode.solved for episode in episodes], bool),
            "policy_version": np.asarray([episode.policy_version for episode in episodes], np.int32),
            "actor": np.asarray([episode.actor for episode in episodes], np.int32),
            "has_level": np.asarray([episode.level is not None for episode in episodes], bool),
        }
        heard: dict[int, dict[str, np.ndarray]] = {}
        for episode in episodes:
            if episode.level is not None:
                heard.setdefault(episode.level_id, episode.level)
        rows = list(heard.values())
        levels = {leaf: np.stack([row[leaf] for row in rows]) for leaf in rows[0]} if rows else {}
        arrays = [*steps.values(), *table.values(), *levels.values()]
        needed = sum(array.nbytes for array in arrays) + METADATA_BYTES * (len(arrays) + 8)
        if not self._make_room(needed):
            self.pending = []
            self.counts["episodes_dropped_full"] += len(episodes)
            return None
        name = f"{self.next_shard:08d}"
        partial = self.path / PARTIAL / name
        final_path = self.path / SHARDS / name
        try:
            with writing(partial):
                check_space(self.path, needed)  # the test hook (`engine.io_errors`); nothing otherwise
                group = _zarr().open_group(partial, mode="w")
                group.attrs.update({"episodes": len(episodes), "steps": int(lengths.sum()),
                                    "solved": int(table["solved"].sum()), "written_at": time.time()})
                _write_arrays(group, STEPS, steps)
                _write_arrays(group, EPISODES, table)
                _write_arrays(group, LEVELS, levels)
                os.replace(partial, final_path)
        except DiskFullError as err:
            shutil.rmtree(partial, ignore_errors=True)  # what fitted of it only takes space
            self._disk_full(err, final)
            return None
        self.pending = []
        if self.disk_full is not None:
            log.info("recording goes on: shard %s written, the disk has room again", name)
            self.disk_full = None
        self.next_shard += 1
        self.bytes_used += folder_bytes(final_path)
        self.counts["episodes_written"] += len(episodes)
        self.counts["steps_written"] += int(lengths.sum())
        self.counts["shards_written"] += 1
        return final_path

    def _disk_full(self, err: DiskFullError, final: bool) -> None:
        """A shard did not fit on the disk: say so (once, then every REMIND_FULL_S), keep the episodes for the
        next try within HELD_WHILE_FULL_BYTES (the oldest dropped first), or lose them if this was the last."""
        now = time.monotonic()
        if final:
            log.error("recording: %s; the %d episodes held are lost", err, len(self.pending))
            self.counts["episodes_dropped_disk_full"] += len(self.pending)
            self.pending = []
        elif self.disk_full is None:
            log.error("recording: %s; the episodes wait in memory (up to %s) and the shard is tried again every "
                      "%.0f s", err, size_text(HELD_WHILE_FULL_BYTES), RETRY_FULL_S)
            self._remind_at = now + REMIND_FULL_S
        elif now >= self._remind_at:
            log.warning("recording still waits for disk space (%d episodes held): %s", len(self.pending), err)
            self._remind_at = now + REMIND_FULL_S
        self.disk_full = err
        self._retry_at = now + RETRY_FULL_S
        held = sum(episode.nbytes for episode in self.pending)
        while self.pending and held > HELD_WHILE_FULL_BYTES:
            held -= self.pending.pop(0).nbytes
            self.counts["episodes_dropped_disk_full"] += 1

    def _make_room(self, needed: int) -> bool:
        """Whether a shard of about `needed` bytes may be written (deleting the oldest shards first if so
        configured); once it may not, the dataset is full for good."""
        if self.full:
            return False
        while self.bytes_used + needed > self.max_bytes:
            shards = _shard_folders(self.path)
            if self.when_full != "drop_oldest" or not shards:
                self.full = True
                log.warning("the dataset in %s is full (%.2f of %.2f GB): recording stops (recorder.when_full="
                            "drop_oldest would delete the oldest shards instead)", self.path, self.bytes_used / 1e9,
                            self.max_bytes / 1e9)
                return False
            oldest = shards[0]
            freed = folder_bytes(oldest)
            shutil.rmtree(oldest)
            self.bytes_used -= freed
            self.counts["shards_dropped"] += 1
            log.info("dataset full: deleted its oldest shard %s (%.1f MB)", oldest.name, freed / 1e6)
        return True
