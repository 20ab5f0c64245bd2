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

Server to client: {"type": "state", ...} (`play.PlaySession.frame`: scene, reward, return, done, outcome, step_ms;
a load adds "level" and "controls", an agent load adds "agent"), or {"type": "error", "message": ...}, after
which the connection stays usable.
"""

from __future__ import annotations

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


class PlayConnection:
    """One play socket: the level it plays, its session and the agent loaded, if any."""

    def __init__(self, library: Library, load_pilot: PilotLoader | None = None):
        self.library = library
        self.load_pilot = load_pilot
        self.source: dict[str, Any] | None = None
        self.pilot: Pilot | None = None
        self.session: PlaySession | None = None

    def handle(self, message: Any) -> dict[str, Any]:
        """The reply to one message; `LevelInputError` (or `library.UnknownLevel`) for a request that cannot be
        served, which the socket reports as an error message."""
        if not isinstance(message, dict):
            raise LevelInputError("a message is a JSON object with a \"type\"")
        kind = message.get("type")
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
        self.session = PlaySession(loaded.level, spec, params, self.pilot)
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
