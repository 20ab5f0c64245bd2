"""Rollout frames in Rerun: the watched environments of a rollout, step by step, on scrubbable timelines.

An actor (or `impulse eval --record`) hands over `RolloutFrames`: the states and actuation its rollout recorded
for the watched environments (`actors.rollout.Watched`, still on the device: `log_rollout` copies them on the
logging thread) and what the trajectory says of each step. Each frame logs, under
`rollouts/<source>/<env>/`:

    scene/...        the scene (`monitor.draw.log_scene`): shapes, motors driven, thrusters firing, and with
                     `contacts` on, scene/contacts: where shapes touch (the engine's narrowphase, rerun here)
    reward           Scalars, the step's reward
    episode_return   Scalars, at the step that ends an episode
    info             TextDocument: level id, policy version, episode; logged when it changes
    episodes         TextLog: one line per finished episode (solved, failed or timed out, return, length)

on four timelines: `env_step` (the environment's steps since the process started), `episode` (episodes it
finished before this one), `episode_step` (step within the episode: select it to scrub the newest episode) and
`wall` (the time the step ran, interpolated over the rollout).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np
import rerun as rr

from impulse.engine.env.state import EnvState
from impulse.engine.levels.drawing import scene_drawing
from impulse.engine.levels.level import level_id_values
from impulse.engine.physics.narrowphase import detect_contacts
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import SimState
from impulse.engine.physics.validate import scene_sizes_of
from impulse.monitor.draw import log_scene, to_view
from impulse.monitor.stream import Monitor

ROLLOUTS = "rollouts"
CONTACT_COLOUR = (255, 40, 40)
CONTACT_RADIUS = 0.04


def env_entity(source: str, name: str) -> str:
    """Entity path of one watched environment's frames."""
    return f"{ROLLOUTS}/{source}/{name}"


@dataclass(frozen=True)
class RolloutFrames:
    """The watched environments of one rollout ([T, W] leading axes) and what to label them with."""

    source: str
    """Who played them (an actor's name, "eval")."""
    states: EnvState
    """State before each step (device or host arrays)."""
    actuation: Any
    """[T, W, J + T] what each action drove (`engine.env.actions.actuation`)."""
    reward: np.ndarray  # [T, W]
    done: np.ndarray  # [T, W] bool
    solved: np.ndarray  # [T, W] bool
    truncated: np.ndarray  # [T, W] bool: timed out
    episode_return: np.ndarray  # [T, W] return of the episode that ends at the step (0 elsewhere)
    policy_version: int
    first_step: int
    """`env_step` of the first frame."""
    episodes_before: np.ndarray
    """[W] episodes each environment finished before the first frame."""
    started_at: float
    """Wall time (time.time()) the rollout started; its steps are spread over `seconds`."""
    seconds: float
    names: tuple[str, ...] = ()
    """Entity name of each environment (default env-<w>)."""
    keep: np.ndarray | None = None
    """[T, W] bool: the frames to log (default all)."""
    contacts: bool = False
    """Also draw the contact points (found again here, on the logging thread: the rollout does not keep them)."""


@functools.cache
def _contact_finder(sizes: SceneSizes) -> Callable[[SimState], tuple[jax.Array, jax.Array]]:
    tables = pair_tables(sizes)

    def touching_points(sim: SimState) -> tuple[jax.Array, jax.Array]:
        found = detect_contacts(sim, tables)
        return found.touching & sim.pair_collides[tables.contact_pair], found.point

    return jax.jit(jax.vmap(touching_points))


def contact_points(sims: SimState) -> list[np.ndarray]:
    """For a sequence of states ([T] leading axis), the world points [k, 2] where shapes touch in each, as the
    engine's narrowphase finds them (pairs joined by a joint excluded, as the solver excludes them)."""
    first = jax.tree.map(lambda x: np.asarray(x)[0], sims)
    touching, points = jax.device_get(_contact_finder(scene_sizes_of(first))(sims))
    return [p[t] for p, t in zip(points, touching, strict=True)]


def _outcome(solved: bool, truncated: bool) -> str:
    return "solved" if solved else "timed out" if truncated else "failed"


def log_rollout(recording: rr.RecordingStream, frames: RolloutFrames) -> int:
    """Log every kept frame (see the module docstring); returns the number logged."""
    states, actuation = jax.device_get((frames.states, frames.actuation))
    steps, watched = np.shape(frames.reward)
    level_ids = level_id_values(np.asarray(states.level.level_id))  # [T, W]
    episode_step = np.asarray(states.timestep)
    keep = np.ones((steps, watched), bool) if frames.keep is None else np.asarray(frames.keep, bool)
    names = frames.names or tuple(f"env-{w}" for w in range(watched))
    logged = 0
    for w in range(watched):
        path = env_entity(frames.source, names[w])
        episode = int(frames.episodes_before[w])
        shown_info = None
        contacts = contact_points(jax.tree.map(lambda x, w=w: x[:, w], states.sim)) if frames.contacts else None
        for t in range(steps):
            if keep[t, w]:
                recording.set_time("env_step", sequence=frames.first_step + t)
                recording.set_time("episode", sequence=episode)
                recording.set_time("episode_step", sequence=int(episode_step[t, w]))
                recording.set_time("wall", timestamp=frames.started_at + frames.seconds * (t + 1) / steps)
                scene = jax.tree.map(lambda x, t=t, w=w: x[t, w], states)
                log_scene(recording, f"{path}/scene", scene_drawing(scene.level, scene.sim, actuation[t, w]))
                if contacts is not None:
                    recording.log(f"{path}/scene/contacts", rr.Points2D(
                        to_view(contacts[t].reshape(-1, 2)), radii=CONTACT_RADIUS,
                        colors=[CONTACT_COLOUR] * len(contacts[t])))
                recording.log(f"{path}/reward", rr.Scalars(float(frames.reward[t, w])))
                info = (int(level_ids[t, w]), episode)
                if info != shown_info:
                    recording.log(f"{path}/info", rr.TextDocument(
                        f"{frames.source} · {names[w]}\nlevel {info[0]:016x}\npolicy version {frames.policy_version}"
                        f"\nepisode {episode}"))
                    shown_info = info
                if frames.done[t, w]:
                    value = float(frames.episode_return[t, w])
                    recording.log(f"{path}/episode_return", rr.Scalars(value))
                    recording.log(f"{path}/episodes", rr.TextLog(
                        f"episode {episode} {_outcome(frames.solved[t, w], frames.truncated[t, w])}: return "
                        f"{value:+.3f} after {int(episode_step[t, w]) + 1} steps on level {info[0]:016x} (policy "
                        f"version {frames.policy_version})",
                        level=rr.TextLogLevel.INFO if frames.solved[t, w] else rr.TextLogLevel.WARN))
                logged += 1
            if frames.done[t, w]:
                episode += 1
    return logged


class RolloutStream:
    """A process's stream of its watched environments: after each rollout it counts their episodes (so the
    `episode` timeline stays right across rollouts it does not stream) and, when the monitor wants frames now,
    offers them. Never waits: the copy off the device and the logging happen on the monitor's thread."""

    def __init__(self, monitor: Monitor, source: str, watch: int, num_steps: int, contacts: bool = False):
        self.monitor, self.source, self.watch, self.num_steps = monitor, source, watch, num_steps
        self.contacts = contacts
        self.rollouts = 0
        self.episodes = np.zeros(watch, np.int64)

    def after_rollout(self, steps: Any, states: EnvState, actuation: Any, policy_version: int, started_at: float,
                      seconds: float) -> None:
        """`steps`: the rollout's trajectory on the host ([T, E] fields reward, done, solved, truncated,
        episode_return); `states`, `actuation`: its watched environments ([T, W], may be on the device)."""
        w = self.watch
        done = np.asarray(steps.done)[:, :w]
        if self.monitor.wants_frames(done.size):
            frames = RolloutFrames(
                source=self.source, states=states, actuation=actuation, reward=np.asarray(steps.reward)[:, :w],
                done=done, solved=np.asarray(steps.solved)[:, :w], truncated=np.asarray(steps.truncated)[:, :w],
                episode_return=np.asarray(steps.episode_return)[:, :w], policy_version=policy_version,
                first_step=self.rollouts * self.num_steps, episodes_before=self.episodes.copy(),
                started_at=started_at, seconds=seconds, contacts=self.contacts)
            self.monitor.offer_frames(lambda recording: log_rollout(recording, frames))
        self.episodes += done.sum(axis=0)
        self.rollouts += 1
