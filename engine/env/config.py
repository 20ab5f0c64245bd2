"""Settings of the Kinetix-compatible task layer.

Defaults follow Kinetix 3.0.x's training setup so that results compare with its published numbers. This is a
plain dataclass (it imports only the engine's config checks and arena constants).
`engine.env.spec.env_from_config` turns it into the environment's static `EnvSpec` and dynamic `EnvParams`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from impulse.engine.arena import SCREEN_PIXELS
from impulse.engine.config_checks import check_range


@dataclass(frozen=True)
class EnvConfig:
    """Which levels an environment plays and how the agent sees and drives them."""

    size: Literal["s", "m", "l"] = "s"
    """Kinetix size class: fixes the number of polygon, circle, joint and thruster slots, hence shapes."""
    levels: str = "handmade"
    """Where levels come from: "handmade" (the bundled hand-made set), "random", or a level file or folder."""
    frame_skip: int = 2
    """Physics sub-steps per agent step; Kinetix trains at 2 (the agent acts at 30 Hz)."""
    max_timesteps: int = 256
    """Agent steps before an episode is cut off."""
    dense_reward_scale: float = 0.2
    """Weight of the shaping term that rewards moving the goal shapes closer together (0.2 as in Kinetix's training
    configs; its level files and EnvParams carry 0.1); 0: the sparse reward alone."""
    observation: Literal["entity", "symbolic", "symbolic_padded", "pixels", "blind"] = "entity"
    """Entity: a structure of per-shape arrays for set/attention networks; symbolic: one flat vector;
    symbolic_padded: the same rows as a [rows, width] matrix tagged with their type (Kinetix's
    symbolic_flat_padded); pixels: the scene drawn as an RGB image (for the "cnn" network); blind: the time step
    alone (Kinetix's blind, a baseline that sees nothing of the scene). The "flat" network takes symbolic,
    symbolic_padded and blind."""
    pixel_downscale: int = 4
    """Pixel observation only: the 500 x 500 screen is drawn at 1 / this resolution (Kinetix's downscale; 4 gives
    125 x 125 images, its default)."""
    action: Literal["multi_discrete", "continuous", "discrete"] = "multi_discrete"
    """How actions map to motors and thrusters; multi-discrete is Kinetix's default."""
    solver: Literal["phased", "jax2d", "jax2d_wipe"] = "phased"
    """Contact schedule of the physics step (`engine.physics.options.SolverOptions.schedule`): "phased" (the fast
    default) or "jax2d" (Jax2D's batch order with lever arms recomputed at every visit: closer to Jax2D's
    trajectories on articulated levels, and slower; see docs/engine.md) or "jax2d_wipe" (the same plus Jax2D's
    padding bug B1, which zeroes the last contact pair's impulses: only for comparing trajectories with Jax2D)."""
    physics_backend: Literal["xla", "pallas"] = "xla"
    """How the phased solver's iterations run (`SolverOptions.backend`): "xla" (the pure-JAX stages) or "pallas" (one
    fused Triton kernel per block of scenes on a CUDA GPU; the XLA stages on any other platform)."""

    def __post_init__(self) -> None:
        for name in ("frame_skip", "max_timesteps", "pixel_downscale"):
            check_range(f"env.{name}", getattr(self, name), at_least=1)
        if SCREEN_PIXELS % self.pixel_downscale:
            raise ValueError(f"env.pixel_downscale must be a divisor of {SCREEN_PIXELS} (the screen's side in "
                             f"pixels), got {self.pixel_downscale}")
        check_range("env.dense_reward_scale", self.dense_reward_scale, at_least=0)
