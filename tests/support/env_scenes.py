"""Shared scenes, specs and one jitted rollout for the environment tests.

Every scene test runs through `rollout`: a jitted `lax.scan` of the vmapped env step over CHUNK agent steps, with
a batch of BATCH environments and a reset batch of NUM_LEVELS levels, so the environment compiles once per spec
(three specs: one per action type) for the whole suite. Scenes are Kinetix size S (4 arena polygons + 1 polygon, 2
circles, 1 joint, 1 thruster).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.env import env
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.env.state import EnvState
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, ROLE_NEUTRAL, Level, level_from_scene, stack_levels
from impulse.engine.physics import SIZE_S, add_circle, add_rectangle, add_revolute_joint, add_thruster, empty_scene

SIZES = SIZE_S
CHUNK = 12  # agent steps per compiled call
BATCH = 2  # environments per call
NUM_LEVELS = 3  # levels in every reset batch
MAX_TIMESTEPS = 20  # short episodes, so the time limit is reached in two calls

SPEC = EnvSpec(sizes=SIZES, max_timesteps=MAX_TIMESTEPS)
CONTINUOUS_SPEC = EnvSpec(sizes=SIZES, max_timesteps=MAX_TIMESTEPS, action="continuous")
DISCRETE_SPEC = EnvSpec(sizes=SIZES, max_timesteps=MAX_TIMESTEPS, action="discrete")
PARAMS = EnvParams()

GREEN_BALL = SIZES.num_polygons  # body index of circle slot 0
SECOND_CIRCLE = SIZES.num_polygons + 1
BOX = SIZES.num_static_polygons  # the one free polygon slot
FLOOR_TOP = 0.4


@functools.partial(jax.jit, static_argnums=0)
def _rollout(spec: EnvSpec, params: EnvParams, state: EnvState, actions, levels: Level):
    step_batch = jax.vmap(env.step, in_axes=(None, None, 0, 0, None))

    def body(s, a):
        obs, s, reward, done, info = step_batch(spec, params, s, a, levels)
        return s, (obs, s, reward, done, info)

    return jax.lax.scan(body, state, actions)


def rollout(state: EnvState, actions, levels: Level, spec: EnvSpec = SPEC, params: EnvParams = PARAMS):
    """Run CHUNK steps of BATCH environments. `actions` is one action per env [BATCH, ...] held for the whole
    chunk, or per step [CHUNK, BATCH, ...]. Returns (final state, per-step (obs, state, reward, done, info)) with
    numpy leaves whose leading axes are [CHUNK, BATCH]."""
    actions = jnp.asarray(actions)
    per_env_ndim = 1 if spec.action != "discrete" else 0
    if actions.ndim == per_env_ndim + 1:
        actions = jnp.broadcast_to(actions, (CHUNK, *actions.shape))
    assert actions.shape[:2] == (CHUNK, BATCH), actions.shape
    final, trace = _rollout(spec, params, state, actions, levels)
    return final, jax.tree.map(np.asarray, trace)


def start(levels: list[Level], reset_levels: Level | None = None, spec: EnvSpec = SPEC):
    """A batch of BATCH environments, env i on levels[i]; returns (state, reset batch). The reset batch defaults
    to the same levels, repeated up to NUM_LEVELS."""
    assert len(levels) == BATCH
    _, states = zip(*(env.reset(spec, PARAMS, level) for level in levels), strict=True)
    state = jax.tree.map(lambda *x: jnp.stack(x), *states)
    if reset_levels is None:
        reset_levels = level_batch(levels)
    return state, reset_levels


def level_batch(levels: list[Level]) -> Level:
    """A reset batch of exactly NUM_LEVELS levels (the list is cycled to fill it)."""
    return stack_levels([levels[i % len(levels)] for i in range(NUM_LEVELS)])


def take(tree, index):
    return jax.tree.map(lambda x: x[index], tree)


def drop_scene(target_role: int, gap: float = 0.3, ball_x: float = 2.5) -> Level:
    """A fixed 1 x 0.5 box of `target_role` on the floor and a green ball (radius 0.2) `gap` metres above it."""
    state = empty_scene(SIZES)
    state, box = add_rectangle(state, (2.5, FLOOR_TOP + 0.25), 1.0, 0.5, fixed=True)
    state, ball = add_circle(state, (ball_x, FLOOR_TOP + 0.5 + 0.2 + gap), 0.2)
    roles = np.zeros(SIZES.num_bodies, np.int32)
    roles[int(box)] = target_role
    roles[int(ball)] = ROLE_GREEN
    return level_from_scene(state, roles=roles)


def overlap_scene(ball_x: float, target_role: int = ROLE_BLUE) -> Level:
    """A green ball already touching a fixed box of `target_role`: the first step decides the episode. The ball's
    x position identifies the level."""
    state = empty_scene(SIZES)
    state, box = add_rectangle(state, (ball_x, 2.0), 1.0, 0.5, fixed=True)
    state, ball = add_circle(state, (ball_x, 2.0 + 0.25 + 0.15), 0.2, fixed=True)
    roles = np.zeros(SIZES.num_bodies, np.int32)
    roles[int(box)] = target_role
    roles[int(ball)] = ROLE_GREEN
    return level_from_scene(state, roles=roles)


def quiet_scene() -> Level:
    """A green ball resting on a neutral floor and nothing else: no reward ever, only the time limit ends it."""
    state = empty_scene(SIZES)
    state, _ = add_circle(state, (2.5, FLOOR_TOP + 0.2), 0.2)
    roles = np.full(SIZES.num_bodies, ROLE_NEUTRAL, np.int32)
    roles[GREEN_BALL] = ROLE_GREEN
    return level_from_scene(state, roles=roles)


THRUST_ANGLE = 0.6  # radians, in the body frame of the thruster's ball
THRUST_POWER = 0.05  # weak, so the ball gains about 1.6 m/s per chunk and stays clear of the walls


def actuator_scene(motor_binding: int = 0, thruster_binding: int = 0) -> Level:
    """No gravity. A fixed box in the air with a wheel (circle 0) pinned at its centre, motor on (joint a = box,
    b = wheel, so +1 drives the wheel counter-clockwise); a free ball (circle 1) with a thruster pointing
    THRUST_ANGLE above +x. All roles neutral."""
    state = empty_scene(SIZES).replace(gravity=jnp.zeros(2, jnp.float32))
    state, box = add_rectangle(state, (1.5, 3.0), 0.4, 0.4, fixed=True)
    state, wheel = add_circle(state, (1.5, 3.0), 0.3)
    state, _ = add_revolute_joint(state, box, wheel, (0.0, 0.0), (0.0, 0.0), motor_on=True)
    state, ball = add_circle(state, (3.5, 2.5), 0.2)
    state, _ = add_thruster(state, ball, rotation=THRUST_ANGLE, power=THRUST_POWER)
    return level_from_scene(state, motor_bindings=[motor_binding], thruster_bindings=[thruster_binding])
