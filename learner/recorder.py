"""The recorder process: it hears the actors' trajectory batches and the levels they play, puts whole episodes
together, and writes them to a dataset on disk (`learner.dataset`) for behaviour cloning and offline analysis.
It takes nothing from the learner's share: it listens on the same keys, in its own process, and the actors
publish the levels they play only while a recorder listens.

One cycle (driven by the shared run loop):
1. hear the level batches the actors are about to play (`actor/played/<actor>`) and keep the newest levels by id
   (at most LEVELS_KEPT);
2. hear trajectory batches (`actor/traj/<actor>`), check them as the learner does (a refused frame is counted by
   its reason) and cut them into episodes per environment (`EpisodeAssembler`): an episode is kept only when the
   recorder saw it from its first step to its last (an actor's first batch starts every environment's first
   episode), so episodes that were under way when the recorder started, or that span a batch it did not hear (a
   gap in the actor's sequence numbers, an actor restart), are left out and counted;
3. hand whole episodes to the dataset writer with their level, and write a shard every `recorder.shard_steps`
   steps or `recorder.flush_s` seconds. An episode whose level has not been heard yet is held until it is, for
   at most `bus.levels.PLAYED_LEVEL_WAIT_S` (the level may arrive just after the batch, or, for a recorder just
   restarted, with the actor's next cycle), and then written without it (the index says which have one).

Killed (kill -9) it loses the episodes not yet in a shard and nothing else: shards appear on disk whole
(`learner.dataset`), and a restarted recorder appends to the same dataset. It stops when the learner has finished
the run, writing what it holds first.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from impulse.actors.follow import LearnerPresence
from impulse.actors.trajectory import TrajectoryBatch
from impulse.actors.wire import TrajectoryWire
from impulse.bus.codec import Rejected
from impulse.bus.levels import PLAYED_LEVEL_WAIT_S, decode_level_batch
from impulse.bus.service import CycleReport, Progress
from impulse.bus.session import Bus
from impulse.bus.status import StatusPublisher
from impulse.bus.trajectories import decode_trajectory
from impulse.curriculum.wire import played_levels_from_message, played_levels_schema
from impulse.engine.levels.level import level_id_values
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.pytree import tree_arrays
from impulse.learner.config import RecorderConfig
from impulse.learner.dataset import DatasetWriter, Episode

log = logging.getLogger("impulse.recorder")

RECORDER_ID = "recorder"
LEVELS_KEPT = 4096
"""Levels kept by id for the episodes still to come (the newest heard)."""
MAX_LEVELS_PER_BATCH = 65536
"""A played-levels frame with more levels than this is refused."""
FIRST_SEQ = 1
"""The sequence number of an actor incarnation's first batch (`actors.process.Actor.seq` counts from it)."""


def step_arrays(steps: Any) -> dict[str, np.ndarray]:
    """What the dataset keeps of each step of a `Trajectory` ([T, E, ...] leaves): the observation, the action
    and the reward, named as the dataset names them (`obs/...`, `action`, `reward`)."""
    return tree_arrays({"obs": steps.obs, "action": steps.action, "reward": steps.reward})


@dataclass
class _Stream:
    """One actor incarnation's batches as the recorder heard them: the last sequence number, and per environment
    the parts of the episode under way and whether it was seen from its start."""

    last_seq: int
    open_parts: list[list[dict[str, np.ndarray]]] = field(default_factory=list)
    whole: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def forget(self, num_envs: int) -> int:
        """Drop every episode under way (they can no longer be whole); returns how many were under way."""
        cut = int(sum(1 for parts in self.open_parts if parts))
        self.open_parts = [[] for _ in range(num_envs)]
        self.whole = np.zeros(num_envs, bool)
        return cut


class EpisodeAssembler:
    """Cuts the trajectory batches of many actors into whole episodes (see the module docstring, step 2)."""

    def __init__(self) -> None:
        self._streams: dict[tuple[str, int], _Stream] = {}
        self.counts = {"episodes_whole": 0, "episodes_cut": 0, "batches_lost": 0}

    def add(self, actor: str, incarnation: int, seq: int, batch: TrajectoryBatch) -> list[tuple[dict[str, Any],
                                                                                                  dict[str, Any]]]:
        """The episodes a batch completes, each as (its steps by name, its facts: level_id, episode_return,
        solved, policy_version, actor)."""
        steps = batch.steps
        num_steps, num_envs = np.shape(steps.reward)
        stream = self._streams.get((actor, incarnation))
        if stream is None:
            for key in [key for key in self._streams if key[0] == actor]:  # an earlier incarnation: gone
                self.counts["episodes_cut"] += self._streams.pop(key).forget(0)
            stream = self._streams[(actor, incarnation)] = _Stream(seq - 1)
            stream.forget(num_envs)
            # An actor's first batch starts every environment's first episode: those are whole.
            stream.whole[:] = seq == FIRST_SEQ
        if seq != stream.last_seq + 1:
            self.counts["batches_lost"] += max(0, seq - stream.last_seq - 1)
            self.counts["episodes_cut"] += stream.forget(num_envs)
        stream.last_seq = seq
        arrays = step_arrays(steps)
        done = np.asarray(steps.done, bool)
        level_ids = level_id_values(steps.level_id)
        facts_at = {"episode_return": np.asarray(steps.episode_return), "solved": np.asarray(steps.solved, bool)}
        version, actor_index = int(batch.behaviour_version), int(batch.actor_id)
        finished: list[tuple[dict[str, Any], dict[str, Any]]] = []
        for env in range(num_envs):
            begin = 0
            for end in np.flatnonzero(done[:, env]):
                part = {name: array[begin:end + 1, env] for name, array in arrays.items()}
                if stream.whole[env]:
                    parts = [*stream.open_parts[env], part]
                    episode = {name: np.concatenate([p[name] for p in parts]) for name in arrays}
                    finished.append((episode, {
                        "level_id": int(level_ids[end, env]),
                        "episode_return": float(facts_at["episode_return"][end, env]),
                        "solved": bool(facts_at["solved"][end, env]),
                        "policy_version": version,
                        "actor": actor_index,
                    }))
                    self.counts["episodes_whole"] += 1
                else:
                    self.counts["episodes_cut"] += 1
                stream.open_parts[env] = []
                stream.whole[env] = True
                begin = end + 1
            if begin < num_steps and stream.whole[env]:
                stream.open_parts[env].append({name: array[begin:, env].copy() for name, array in arrays.items()})
        return finished


class LevelWait:
    """Whole episodes whose level the recorder has not heard yet, held for at most `wait_s` (module docstring,
    step 3)."""

    def __init__(self, wait_s: float = PLAYED_LEVEL_WAIT_S) -> None:
        self.wait_s = wait_s
        self._held: list[tuple[float, Episode]] = []  # (when it goes without its level, the episode)

    def __len__(self) -> int:
        return len(self._held)

    def hold(self, episode: Episode, now: float) -> None:
        self._held.append((now + self.wait_s, episode))

    def settle(self, levels: Mapping[int, dict[str, np.ndarray]], now: float, final: bool) -> list[Episode]:
        """The held episodes whose level is now in `levels` (given it), then those whose wait is over, or every
        other one when `final` (still without it); the rest stay held."""
        settled: list[Episode] = []
        still: list[tuple[float, Episode]] = []
        for deadline, episode in self._held:
            level = levels.get(episode.level_id)
            if level is not None:
                settled.append(episode._replace(level=level))
            elif final or now >= deadline:
                settled.append(episode)
            else:
                still.append((deadline, episode))
        self._held = still
        return settled


class RecorderService:
    """The recorder's state and its run-loop `cycle` (see the module docstring)."""

    def __init__(self, config: RecorderConfig, *, bus: Bus, writer: DatasetWriter, template: TrajectoryBatch,
                 sizes: SceneSizes, wire_compact: bool, status_every_s: float, ident: str = RECORDER_ID):
        """`template`: the shapes of the run's trajectory batches (`actors.wire.trajectory_template`);
        `wire_compact`: the actors send the compact format (`bus.wire_compact`)."""
        self.config = config
        self.bus = bus
        self.writer = writer
        self.ident = ident
        self._wire = TrajectoryWire(template, sizes, compact=wire_compact)
        self._levels_schema = played_levels_schema(sizes)
        keys = bus.keys
        self._trajectories = bus.inbox(keys.traj_all, 64)
        self._played = bus.inbox(keys.levels_played_all, 64, drop_oldest=True)
        self.learner = LearnerPresence(bus)
        self._status = StatusPublisher(bus, status_every_s)
        self.assembler = EpisodeAssembler()
        self.levels: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        self.counts = {"batches": 0, "episodes_without_level": 0, "level_batches": 0}
        self.awaiting_level = LevelWait()
        self._started = time.monotonic()

    def _hear_levels(self) -> None:
        for received in self._played.poll():
            source = received.key.rsplit("/", 1)[-1]
            try:
                message = decode_level_batch(received.payload, self.bus.keys.run)
                levels = played_levels_from_message(message, self._levels_schema, MAX_LEVELS_PER_BATCH)
            except Rejected as err:
                self.bus.rejects.record(err.reason, source, err.detail)
                continue
            self.counts["level_batches"] += 1
            for row, level_id in enumerate(level_id_values(levels["level_id"])):
                self.levels[int(level_id)] = {name: array[row] for name, array in levels.items()}
                self.levels.move_to_end(int(level_id))
            while len(self.levels) > LEVELS_KEPT:
                self.levels.popitem(last=False)

    def _hear_trajectories(self) -> list[Episode]:
        episodes: list[Episode] = []
        for received in self._trajectories.poll():
            source = received.key.rsplit("/", 1)[-1]  # the actor, as the key names it
            try:
                message, incarnation = decode_trajectory(received.payload, self.bus.keys.run,
                                                         self._wire.max_frame_bytes, self._wire.format)
                batch = self._wire.checked(message)
            except Rejected as err:
                self.bus.rejects.record(err.reason, source, err.detail)
                continue
            self.counts["batches"] += 1
            for steps, facts in self.assembler.add(source, incarnation, message.seq, batch):
                level = self.levels.get(facts["level_id"])
                episode = Episode(steps=steps, level=level, **facts)
                if level is None:
                    self.awaiting_level.hold(episode, time.monotonic())
                else:
                    episodes.append(episode)
        return episodes

    def _settled(self, final: bool) -> list[Episode]:
        """The held episodes ready to write (`LevelWait.settle`), counting those that go without their level."""
        settled = self.awaiting_level.settle(self.levels, time.monotonic(), final)
        self.counts["episodes_without_level"] += sum(episode.level is None for episode in settled)
        return settled

    def cycle(self) -> CycleReport | None:
        if self._status.due():
            self._status.publish(self.status())
        self.learner.poll()
        self._hear_levels()
        episodes = self._hear_trajectories()
        episodes += self._settled(final=False)
        self.writer.add(episodes)
        waiting = self.writer.pending_steps
        if waiting >= self.config.shard_steps or (
                waiting and time.monotonic() - self.writer.last_flush >= self.config.flush_s):
            self._flush()
        if not episodes:
            return None
        steps = sum(episode.length for episode in episodes)
        solved = sum(episode.solved for episode in episodes)
        return CycleReport(env_steps=steps, updates=0, metrics={"episodes": float(len(episodes)),
                                                                 "solve_rate": solved / len(episodes)})

    def _flush(self, final: bool = False) -> None:
        """Write the whole episodes held as a shard (on a full disk the writer keeps them and tries again later;
        `final`: the last try, `learner.dataset`)."""
        episodes = len(self.writer.pending)
        shard = self.writer.flush(final=final)
        if shard is not None:
            log.info("wrote shard %s: %d episodes (%.1f MB of %.1f GB used)", shard.name, episodes,
                     self.writer.bytes_used / 1e6, self.writer.max_bytes / 1e9)

    def status(self) -> dict[str, Any]:
        writer = self.writer
        return {
            "role": self.bus.role,
            "name": self.ident,
            "path": str(writer.path),
            "pending_steps": writer.pending_steps,
            "bytes_used": writer.bytes_used,
            "max_bytes": writer.max_bytes,
            "full": writer.full,
            "levels_known": len(self.levels),
            "episodes_awaiting_level": len(self.awaiting_level),
            "rejected": self.bus.rejects.counts(),
            **writer.counts,
            **self.assembler.counts,
            **self.counts,
        }

    def start(self) -> None:
        """Nothing to prepare: it records what it hears."""

    def progress(self) -> Progress:
        return Progress()

    def save(self, summary: dict[str, float]) -> None:
        """Write the whole episodes held (a shard)."""
        self._flush()

    def finished(self) -> bool:
        if self.learner.finished:
            log.info("the learner finished the run: the recorder writes what it holds and stops")
            return True
        return False

    def close(self) -> None:
        """Write the whole episodes held (those still without their level as they are), and tell whoever watches
        where it got to."""
        self.writer.add(self._settled(final=True))
        self._flush(final=True)
        self._status.publish(self.status())
