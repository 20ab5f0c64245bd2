"""Agent actions and how they drive motors and thrusters (Kinetix's three action types, same mapping).

Every action type is first turned into one unified vector u of NM + NT = 4 + 2 values (one per motor binding,
then one per thruster binding). A joint reads u[its motor binding] clipped to [-1, 1]; a thruster reads
u[NM + its thruster binding] clipped to [0, 1]. Several joints may share a binding; a binding no joint uses
does nothing.

- multi_discrete: int [6], categories [3, 3, 3, 3, 2, 2]; motor dims 0 -> 0, 1 -> +1, 2 -> -1; thruster dims
  0 -> 0, 1 -> 1.
- continuous: float [6]; u = a (so motors end up in [-1, 1], thrusters in [0, 1]).
- discrete: int scalar in [0, 11); a < 8: motor a // 2 gets -1 if a is even, +1 if odd; 8: no-op; a >= 9:
  thruster a - 9 gets 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.env.spec import EnvSpec
from impulse.engine.levels.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, Level

Array = jax.Array

NUM_ACTION_DIMS = NUM_MOTOR_BINDINGS + NUM_THRUSTER_BINDINGS  # 6: the unified action vector
MOTOR_CATEGORIES = 3  # off, +1, -1
THRUSTER_CATEGORIES = 2  # off, on
NUM_DISCRETE_ACTIONS = 2 * NUM_MOTOR_BINDINGS + 1 + NUM_THRUSTER_BINDINGS  # 11
DISCRETE_NOOP = 2 * NUM_MOTOR_BINDINGS  # 8


@dataclass(frozen=True)
class ActionSpace:
    """What a policy must output for an action type.

    - multi_discrete: `shape` (6,), int32; dimension i is a categorical over `nvec[i]` values; `num_logits` =
      sum(nvec) = 16 (logits of all dimensions laid end to end, dimension 0 first).
    - discrete: `shape` (), int32; one categorical over `nvec[0]` = 11 values; `num_logits` = 11.
    - continuous: `shape` (6,), float32 in [`low`, `high`] per dimension; `nvec` is empty; `num_logits` = 6 (one
      mean per dimension).
    """

    kind: str
    shape: tuple[int, ...]
    dtype: str
    nvec: tuple[int, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    @property
    def num_logits(self) -> int:
        return sum(self.nvec) if self.nvec else int(np.prod(self.shape))


def action_space(spec: EnvSpec) -> ActionSpace:
    motors, thrusters = NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS
    if spec.action == "multi_discrete":
        nvec = (MOTOR_CATEGORIES,) * motors + (THRUSTER_CATEGORIES,) * thrusters
        return ActionSpace("multi_discrete", (NUM_ACTION_DIMS,), "int32", nvec, (), ())
    if spec.action == "discrete":
        return ActionSpace("discrete", (), "int32", (NUM_DISCRETE_ACTIONS,), (), ())
    low = (-1.0,) * motors + (0.0,) * thrusters
    high = (1.0,) * NUM_ACTION_DIMS
    return ActionSpace("continuous", (NUM_ACTION_DIMS,), "float32", (), low, high)


def unified_action(spec: EnvSpec, action: Array) -> Array:
    """The agent's action as the unified vector u [6] float32 (before clipping)."""
    if spec.action == "multi_discrete":
        a = jnp.asarray(action, jnp.int32)
        motor = a[:NUM_MOTOR_BINDINGS]
        motor_u = jnp.where(motor == 1, 1.0, jnp.where(motor == 2, -1.0, 0.0))
        thruster_u = (a[NUM_MOTOR_BINDINGS:] == 1).astype(jnp.float32)
        return jnp.concatenate([motor_u, thruster_u])
    if spec.action == "continuous":
        return jnp.asarray(action, jnp.float32).reshape(NUM_ACTION_DIMS)
    a = jnp.asarray(action, jnp.int32).reshape(())
    is_motor = a < DISCRETE_NOOP
    dim = jnp.where(is_motor, a // 2, jnp.where(a > DISCRETE_NOOP, a - (DISCRETE_NOOP + 1) + NUM_MOTOR_BINDINGS, -1))
    value = jnp.where(is_motor, jnp.where(a % 2 == 0, -1.0, 1.0), 1.0)
    return jnp.where(jnp.arange(NUM_ACTION_DIMS) == dim, value, 0.0)


def engine_actions(u: Array, level: Level) -> Array:
    """Per-slot engine actions [J + T]: each joint's and thruster's value through its binding, clipped."""
    motor = jnp.clip(u[level.motor_bindings], -1.0, 1.0)
    thrust = jnp.clip(u[NUM_MOTOR_BINDINGS + level.thruster_bindings], 0.0, 1.0)
    return jnp.concatenate([motor, thrust])


def actuation(spec: EnvSpec, action: Array, level: Level) -> Array:
    """What one agent action drives in `level`: the per-slot engine actions [J + T] (one environment)."""
    return engine_actions(unified_action(spec, action), level)


def noop_action(spec: EnvSpec) -> Array:
    """The action that drives nothing (all zeros; 8 for discrete)."""
    space = action_space(spec)
    if space.kind == "discrete":
        return jnp.asarray(DISCRETE_NOOP, jnp.int32)
    return jnp.zeros(space.shape, space.dtype)


def random_action(spec: EnvSpec, key: Array) -> Array:
    """A uniformly random action of one environment (vmap over keys for a batch). Continuous thrusters are drawn
    in [0, 1] (as Kinetix's own sampler does): a draw in [-1, 1] would clip to "off" half the time."""
    space = action_space(spec)
    if space.kind == "multi_discrete":
        return jax.random.randint(key, space.shape, 0, jnp.asarray(space.nvec, jnp.int32), jnp.int32)
    if space.kind == "discrete":
        return jax.random.randint(key, (), 0, NUM_DISCRETE_ACTIONS, jnp.int32)
    return jax.random.uniform(key, space.shape, jnp.float32, jnp.asarray(space.low), jnp.asarray(space.high))
