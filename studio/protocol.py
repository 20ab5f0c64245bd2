"""The play socket's messages (`/ws/play`), one connection's state and the reply to each message, apart from the
ASGI plumbing so that it reads (and is tested) as plain calls. docs/studio.md lists the messages.

Client to server (JSON objects; an optional "seq" is echoed in the reply, for measuring the round trip):

- {"type": "load", "set": S, "name": N} or {"type": "load", "level": {...Kinetix JSON...}}: play this level (a
  gallery level, or the editor's unsaved one) from its start;
- {"type": "reset"}: start the episode again;
- {"type": "step", "action": [m0, m1, m2, m3, t0, t1]}: one agent step with a multi-discrete action;
- {"type": "step", "agent": true}: one agent step with the loaded agent's action;
- {"type": "agent", "checkpoint": PATH}: load a policy to watch (null to unload); the level is reloaded in the
  agent's size, or refused with the reason when it does not fit.

Any message may carry "progress": true: while its reply takes longer than a second, the server sends
{"type": "progress", "seq", "what", "elapsed_s"} every second first (what the connection is doing: loading the
agent, compiling the environment or the policy on their first use, `play.PlaySession.warm_up`), so a page can
say what it waits for. Without it, every message gets exactly one reply, as before.

Server to client: {"type": "state", ...} (`play.PlaySession.frame`: scene, reward, return, done, outcome, step_ms;
a load adds "level" and "controls", an agent load adds "agent"), or {"type": "error", "message": ...}, after
which the connection stays usable. Loads and agent loads compile what stepping needs before they reply
(`play.PlaySession.warm_up`), so no step waits for a compile.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.kinetix_json import KinetixLevel
from impulse.engine.levels.summary import describe_sizes, size_class
from impulse.studio.level_io import LevelInputError, load_document, load_file
from impulse.studio.library import Library
from impulse.studio.play import Pilot, PlaySession

PilotLoader = Callable[[str], Pilot]
"""Loads a policy from a checkpoint or run directory; raises `LevelInputError` (or ValueError) with the reason."""


def controls(loaded: KinetixLevel) -> dict[str, list[int]]:
    """The motor and thruster bindings the level actually uses (the page shows keys for these)."""
    joints, thrusters = loaded.state.joints, loaded.state.thrusters
    motorised = np.asarray(joints.active) & np.asarray(joints.motor_on) & ~np.asarray(joints.is_fixed_joint)
    fired = np.asarray(thrusters.active)
    return {"motors": sorted({int(b) for b in np.asarray(loaded.motor_bindings)[motorised]}),
            "thrusters": sorted({int(b) for b in np.asarray(loaded.thruster_bindings)[fired]})}


class PilotCache:
    """`load_pilot` once per checkpoint, shared by every play connection and the gallery's scoring: a second "Load
    agent" of the same checkpoint costs nothing, and the same agent object means the same compiled programs. A
    checkpoint folder whose contents changed (a running run wrote a newer checkpoint) is loaded again."""

    def __init__(self, load_pilot: PilotLoader):
        self.load_pilot = load_pilot
        self._pilots: dict[str, tuple[tuple[float, ...], Pilot]] = {}
        self._lock = threading.Lock()

    @staticmethod
    def _stamp(checkpoint: str) -> tuple[float, ...]:
        """The modification times of the checkpoint path and of its `checkpoints` folder (where a run adds steps)."""
        stamps = []
        for path in (Path(checkpoint), Path(checkpoint) / "checkpoints"):
            try:
                stamps.append(path.stat().st_mtime)
            except OSError:
                stamps.append(-1.0)
        return tuple(stamps)

    def cached(self, checkpoint: str) -> bool:
        """Whether `checkpoint` is loaded already (and unchanged): loading it again is instant."""
        with self._lock:
            entry = self._pilots.get(checkpoint)
        return entry is not None and entry[0] == self._stamp(checkpoint)

    def __call__(self, checkpoint: str) -> Pilot:
        stamp = self._stamp(checkpoint)
        with self._lock:  # one load at a time: two pages asking for the same agent load it once
            entry = self._pilots.get(checkpoint)
            if entry is None or entry[0] != stamp:
                entry = (stamp, self.load_pilot(checkpoint))
                self._pilots[checkpoint] = entry
            return entry[1]


class PlayConnection:
    """One play socket: the level it plays, its session and the agent loaded, if any. `phase` says what the
    message being handled is doing now (set from the worker thread, read by the socket's loop for progress)."""

    def __init__(self, library: Library, load_pilot: PilotLoader | None = None):
        self.library = library
        self.load_pilot = load_pilot
        self.source: dict[str, Any] | None = None
        self.pilot: Pilot | None = None
        self.session: PlaySession | None = None
        self.phase: str | None = None
        self.phase_since = time.monotonic()

    def report(self, what: str) -> None:
        """Record what the connection is doing now (`phase`), for the page's wait message."""
        self.phase, self.phase_since = what, time.monotonic()

    def handle(self, message: Any) -> dict[str, Any]:
        """The reply to one message; `LevelInputError` (or `library.UnknownLevel`) for a request that cannot be
        served, which the socket reports as an error message."""
        if not isinstance(message, dict):
            raise LevelInputError("a message is a JSON object with a \"type\"")
        kind = message.get("type")
        self.report({"load": "loading the level", "agent": "loading the agent", "reset": "resetting the level",
                     "step": "stepping"}.get(kind, "working"))
        if kind == "load":
            return self._load(message)
        if kind == "agent":
            return self._agent(message.get("checkpoint"))
        if self.session is None:
            raise LevelInputError("no level loaded: send {\"type\": \"load\", ...} first")
        if kind == "reset":
            return self.session.reset()
        if kind == "step":
            return self.session.step(None if message.get("agent") is True else message.get("action"))
        raise LevelInputError(f"unknown message type {kind!r}; known: load, reset, step, agent")

    def _read(self, source: dict[str, Any], spec_sizes=None) -> KinetixLevel:
        if "level" in source:
            return load_document(source["level"], spec_sizes)
        set_id, name = source.get("set"), source.get("name")
        if not isinstance(set_id, str) or not isinstance(name, str):
            raise LevelInputError("load needs \"set\" and \"name\" (a gallery level) or \"level\" (a level's JSON)")
        return load_file(self.library.path(set_id, name), spec_sizes, validate=True)

    def _load(self, source: dict[str, Any]) -> dict[str, Any]:
        sizes = None if self.pilot is None else self.pilot.spec.sizes
        if sizes is not None:
            own = self._read(source).file_sizes
            if own is not None and not own.fits_in(sizes):
                raise LevelInputError(f"the agent {self.pilot.name} plays levels of size {describe_sizes(sizes)}; "
                                      f"this level is {describe_sizes(own)} and does not fit: unload the agent to "
                                      "play it yourself")
        loaded = self._read(source, sizes)
        if self.pilot is not None:
            spec, params = self.pilot.spec, self.pilot.env_params
        else:
            spec = EnvSpec(sizes=loaded.sizes, solver=loaded.options, frame_skip=loaded.frame_skip)
            params = EnvParams(sim=loaded.params)
        session = PlaySession(loaded.level, spec, params, self.pilot)
        session.warm_up(self.report)
        self.session = session
        self.source = {key: source[key] for key in ("set", "name", "level") if key in source}
        reply = self.session.reset()
        reply["level"] = {"set": source.get("set"), "name": source.get("name"),
                          "size": size_class(loaded.file_sizes or loaded.sizes), "max_steps": spec.max_timesteps,
                          "seconds_per_step": spec.frame_skip * float(params.sim.dt)}
        reply["controls"] = controls(loaded)
        reply["agent"] = None if self.pilot is None else self.pilot.name
        return reply

    def _agent(self, checkpoint: Any) -> dict[str, Any]:
        if checkpoint is None:
            self.pilot = None
        else:
            if self.load_pilot is None:
                raise LevelInputError("this studio cannot load agents")
            if not isinstance(checkpoint, str) or not checkpoint:
                raise LevelInputError("agent needs \"checkpoint\": a run directory or a checkpoint folder")
            self.report(f"loading the agent {checkpoint}")
            pilot = self.load_pilot(str(Path(checkpoint).expanduser()))
            previous, self.pilot = self.pilot, pilot
            if self.source is not None:
                try:
                    return self._load(self.source)
                except LevelInputError:
                    self.pilot = previous
                    raise
        if self.source is None:
            return {"type": "agent", "agent": None if self.pilot is None else self.pilot.name}
        return self._load(self.source)
