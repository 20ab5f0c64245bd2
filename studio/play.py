"""Playing one level on the server: one environment of the engine (`engine.env.env.reset` and `step`, unchanged),
stepped one agent step per request, by the user's keys or by an agent's policy.

Compiled once per environment spec (size, frame skip, solver, observation): the engine's jitted step takes the
level as an argument, so every level of a size shares one compilation, with every other user of the same spec in
this process and (with JAX's persistent cache) the next. The environment resets itself when an episode ends (the
engine's auto-reset); the step's reply says how the episode ended and what it returned.

Actions are Kinetix's multi-discrete vector of 6 integers: four motor bindings (0 off, 1 forwards, 2 backwards)
and two thruster bindings (0 off, 1 on), `engine.env.actions`.

Compiling happens when a level or an agent is loaded, never in a step (`PlaySession.warm_up`): the first use of an
environment spec compiles its reset, step and drive readout, and the first use of an agent compiles its policy,
each once per process, one at a time, and each said to the page while it lasts (the `report` callback), so
stepping, once it starts, never stops for a compile. Every array a session hands the jitted functions is committed
to one device (`PlaySession.device`): JAX compiles a function anew for arguments placed differently, and a
restored agent's parameters are committed, so its actions were, and so the state the step returned from them was,
while a person's actions were not. (Watching used to compile three times over on its first steps: the policy on
the agent's first step, the environment step again for the agent's committed action, then the policy and the step
once more for the committed observation and state, 20 to 40 s each on a busy 2-core machine, the page's step
counter standing still, with no word, all the while.)
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from impulse.engine.env.actions import NUM_ACTION_DIMS, action_space, actuation
from impulse.engine.env.env import reset, step
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.drawing import scene_drawing
from impulse.engine.levels.level import Level, stack_levels
from impulse.engine.levels.summary import size_class
from impulse.studio.level_io import LevelInputError
from impulse.studio.scene import scene_json

Array = jax.Array
Report = Callable[[str], None]
"""Told what a long piece of work is doing now ("compiling the agent's policy for size S (first use)")."""

_WARMED: set[tuple[str, Any]] = set()
"""What this process has compiled for play: ("env", spec) and ("policy", agent) (both hashable, static args)."""
_WARMING = threading.Lock()
"""One compile at a time: a second connection needing the same program waits for it instead of compiling it too."""


def _silent(what: str) -> None:
    """A `Report` that tells nobody."""


drive_of = jax.jit(actuation, static_argnums=0)
"""What one action drives in a level ([J + T] per slot, for drawing motors and flames), jitted: one dispatch."""


@functools.partial(jax.jit, static_argnums=0)
def agent_action(agent: Any, params: Any, obs: Any, key: Array) -> Array:
    """The agent's sampled action for one observation (as `impulse eval` samples, not greedily)."""
    batched = jax.tree.map(lambda x: x[None], obs)
    return agent.act(params, batched, key)[0][0]


@dataclass(frozen=True)
class Pilot:
    """A loaded policy that can play: its `learner.agent.Agent` (whose spec fixes the level size and the
    observation), its parameters, the environment parameters it was trained with and a name for the page."""

    agent: Any
    params: Any
    env_params: EnvParams
    name: str

    @property
    def spec(self) -> EnvSpec:
        return self.agent.spec


def check_action(spec: EnvSpec, action: Any) -> np.ndarray:
    """A multi-discrete action from the request, or `LevelInputError` saying what an action looks like."""
    space = action_space(spec)
    wrong = LevelInputError(f"an action is a list of {NUM_ACTION_DIMS} integers: 4 motors (0 off, 1 forwards, "
                            f"2 backwards), then 2 thrusters (0 off, 1 on); got {action!r}")
    if not isinstance(action, list) or len(action) != NUM_ACTION_DIMS:
        raise wrong
    if any(isinstance(a, bool) or not isinstance(a, int) or not 0 <= a < n for a, n in zip(action, space.nvec)):
        raise wrong
    return np.asarray(action, np.int32)


class PlaySession:
    """One environment on one level. `reset` and `step` return the reply sent to the page (see `frame`)."""

    def __init__(self, level: Level, spec: EnvSpec, params: EnvParams, pilot: Pilot | None = None, seed: int = 0):
        if spec.action != "multi_discrete":
            raise LevelInputError(f"play drives multi-discrete actions; this environment uses {spec.action}")
        self.device = jax.devices()[0]
        """Where every argument of the jitted functions lives (committed), so each compiles once (module doc)."""
        self.host_level = jax.device_get(level)  # the episode's level, for drawing: it never changes in a session
        self.level = self._put(level)
        self.levels = self._put(stack_levels([level]))
        self.spec = spec
        self.params = self._put(params)
        self.pilot = pilot
        self.agent_params = self._put(pilot.params) if pilot is not None else None
        self.key = self._put(jax.random.PRNGKey(seed))
        self.obs: Any = None
        self.state: Any = None

    def _put(self, tree: Any) -> Any:
        """`tree`'s arrays committed to the session's device (no copy for those already there)."""
        return jax.device_put(tree, self.device)

    def warm_up(self, report: Report = _silent) -> None:
        """Compile what stepping this session needs and this process has not compiled yet: the environment's reset,
        step and drive readout for its spec, and the pilot's policy; `report` is told each compile as it starts.
        Runs them once on the level's start and throws the results away."""
        size = size_class(self.spec.sizes)
        work = [(("env", self.spec), f"compiling the environment for size {size} (first use)", self._warm_env)]
        if self.pilot is not None:
            work.append((("policy", self.pilot.agent), f"compiling the agent's policy for size {size} (first use)",
                         self._warm_policy))
        for key, what, run in work:
            if key in _WARMED:
                continue
            if not _WARMING.acquire(blocking=False):
                report(f"waiting for another compile to finish before {what}")
                _WARMING.acquire()
            try:
                if key not in _WARMED:
                    report(what)
                    run()
                    _WARMED.add(key)
            finally:
                _WARMING.release()

    def _warm_env(self) -> None:
        obs, state = reset(self.spec, self.params, self.level)
        noop = self._put(np.zeros(NUM_ACTION_DIMS, np.int32))  # as the steps' actions: int32 [6], committed
        stepped = step(self.spec, self.params, state, noop, self.levels)
        jax.block_until_ready((stepped, drive_of(self.spec, noop, self.level)))

    def _warm_policy(self) -> None:
        obs, _ = reset(self.spec, self.params, self.level)
        _, key = jax.random.split(self.key)  # as `step` splits its key
        jax.block_until_ready(agent_action(self.pilot.agent, self.agent_params, obs, key))

    def reset(self) -> dict[str, Any]:
        start = time.perf_counter()
        self.obs, self.state = reset(self.spec, self.params, self.level)
        jax.block_until_ready(self.state)
        step_ms = (time.perf_counter() - start) * 1e3
        return self.frame(step_ms, reward=0.0, done=False, outcome=None, episode_return=0.0, drive=None)

    def step(self, action: Any = None) -> dict[str, Any]:
        """One agent step with `action` (a multi-discrete list), or the pilot's action when `action` is None."""
        if self.state is None:
            raise LevelInputError("no level loaded: send a load message first")
        start = time.perf_counter()
        if action is None:
            if self.pilot is None:
                raise LevelInputError("no agent loaded: send an action, or load a checkpoint first")
            self.key, key = jax.random.split(self.key)
            chosen = agent_action(self.pilot.agent, self.agent_params, self.obs, key)
        else:
            chosen = self._put(check_action(self.spec, action))
        # The engine's own jitted step, so play shares its compilation with every other user of this spec.
        self.obs, self.state, reward, done, info = step(self.spec, self.params, self.state, chosen, self.levels)
        jax.block_until_ready(self.state)
        step_ms = (time.perf_counter() - start) * 1e3
        drive = drive_of(self.spec, chosen, self.level)
        reward, done, info, drive, chosen = jax.device_get((reward, done, info, drive, chosen))
        outcome = None
        if done:
            outcome = next((name for name in ("solved", "failed", "timed_out", "nan") if info[name]), "ended")
        return self.frame(step_ms, float(reward), bool(done), outcome, float(info["returned_episode_return"]),
                          np.asarray(drive), np.asarray(chosen).tolist())

    def frame(self, step_ms: float, reward: float, done: bool, outcome: str | None, episode_return: float,
              drive: np.ndarray | None, action: list[int] | None = None) -> dict[str, Any]:
        """The reply: the scene after the step (after the auto-reset when the episode ended: `done` and
        `outcome` tell), the reward, the episode's return and step count, the action taken and the server's step
        time in milliseconds (the jitted step, device work included)."""
        sim, timestep, running_return = jax.device_get((self.state.sim, self.state.timestep,
                                                          self.state.episode_return))
        return {
            "type": "state",
            "t": int(timestep),
            "reward": round(reward, 5),
            "return": round(episode_return if done else float(running_return), 5),
            "done": done,
            "outcome": outcome,
            "action": action,
            "step_ms": round(step_ms, 3),
            "scene": scene_json(scene_drawing(self.host_level, sim, drive)),
        }
