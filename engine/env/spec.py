"""What an environment is: a static `EnvSpec` (shapes and modes; changing it recompiles) and a dynamic `EnvParams`
pytree (physics constants and the reward scale; traced, so changing them does not recompile).

Both are built from the user-facing `EnvConfig` by `env_from_config`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from impulse.engine.env.config import EnvConfig
from impulse.engine.env.pixels import pixel_geometry
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SIZE_S, SceneSizes, size_preset
from impulse.engine.pytree import pytree_dataclass

ObservationKind = Literal["entity", "symbolic", "symbolic_padded", "pixels", "blind"]
ActionKind = Literal["multi_discrete", "continuous", "discrete"]
OBSERVATION_KINDS = ("entity", "symbolic", "symbolic_padded", "pixels", "blind")
ACTION_KINDS = ("multi_discrete", "continuous", "discrete")


@dataclass(frozen=True)
class EnvSpec:
    """Static description of an environment: a jit static argument (hashable)."""

    sizes: SceneSizes = SIZE_S
    solver: SolverOptions = SolverOptions()
    """How the physics step solves each scene (schedule, backend, iterations, warm start)."""
    frame_skip: int = 2
    """Physics sub-steps per agent step, all with the same action."""
    max_timesteps: int = 256
    """Agent steps after which an episode is cut off (done, `timed_out`)."""
    observation: ObservationKind = "entity"
    action: ActionKind = "multi_discrete"
    pixel_downscale: int = 4
    """Pixel observation: draw the 500 x 500 screen at 1 / this resolution (Kinetix's downscale)."""

    def __post_init__(self) -> None:
        if self.frame_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {self.frame_skip}")
        if self.max_timesteps < 1:
            raise ValueError(f"max_timesteps must be >= 1, got {self.max_timesteps}")
        if self.observation not in OBSERVATION_KINDS:
            raise ValueError(f"unknown observation {self.observation!r}; choose one of {', '.join(OBSERVATION_KINDS)}")
        if self.action not in ACTION_KINDS:
            raise ValueError(f"unknown action {self.action!r}; choose one of {', '.join(ACTION_KINDS)}")
        pixel_geometry(self.pixel_downscale)  # raises on a downscale that does not divide the screen


@pytree_dataclass
class EnvParams:
    """Dynamic environment parameters (all leaves traced)."""

    sim: SimParams = field(default_factory=SimParams)
    dense_reward_scale: float = 0.1
    """Weight of the shaping term -(distance - last distance); 0.1 as in Kinetix's EnvParams and level files
    (Kinetix's training configs use 0.2)."""


def env_from_config(config: EnvConfig, sim: SimParams | None = None) -> tuple[EnvSpec, EnvParams]:
    """The spec and params an `EnvConfig` describes (physics constants default to Jax2D's)."""
    spec = EnvSpec(
        sizes=size_preset(config.size),
        solver=SolverOptions(schedule=config.solver, backend=config.physics_backend),
        frame_skip=config.frame_skip,
        max_timesteps=config.max_timesteps,
        observation=config.observation,
        action=config.action,
        pixel_downscale=config.pixel_downscale,
    )
    params = EnvParams(sim=sim if sim is not None else SimParams(), dense_reward_scale=config.dense_reward_scale)
    return spec, params

