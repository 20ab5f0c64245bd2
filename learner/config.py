"""Training configuration: PPO, the network, checkpoints and the run as a whole.

Defaults are Kinetix's PPO setup (entity transformer, 2,048 environments, 256-step rollouts), so a run with no
overrides is comparable with the published baselines. These are plain dataclasses filled in by issue 5 (learner
and fused trainer) and the distributed-mode issues; `deploy.config` loads them from TOML and `key=value`
overrides, so every field needs a default and a type it understands.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from engine.env.config import EnvConfig


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters, plus the correction for data collected by an older policy (distributed actors)."""

    num_envs: int = 2048
    num_steps: int = 256
    """Environment steps per rollout, per environment."""
    num_minibatches: int = 32
    """Minibatches split across environments (whole sequences), so it must divide num_envs."""
    update_epochs: int = 8
    learning_rate: float = 1e-4
    anneal_lr: bool = True
    """Decay the learning rate linearly to zero over the run."""
    gamma: float = 0.995
    gae_lambda: float = 0.9
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    correction: Literal["vtrace", "none"] = "vtrace"
    """Off-policy correction for trajectories from a lagging policy; "none" is plain on-policy PPO."""
    max_policy_lag: int = 4
    """Trajectories older than this many policy versions are dropped rather than corrected."""

    def __post_init__(self) -> None:
        if self.num_envs % self.num_minibatches:
            raise ValueError(
                f"num_minibatches ({self.num_minibatches}) must divide num_envs ({self.num_envs}), "
                "because minibatches are whole environment sequences"
            )


@dataclass(frozen=True)
class NetworkConfig:
    """Policy and value network shape. Kinetix's default is the entity transformer with 5 x 128 tanh heads."""

    kind: Literal["entity", "transformer"] = "transformer"
    """"transformer": attention over shapes with joint/thruster message passing; "entity": a cheaper
    permutation-invariant MLP over the same entity observation."""
    width: int = 128
    depth: int = 5
    """Dense layers in each of the separate actor and critic heads."""
    transformer_layers: int = 2
    num_heads: int = 8
    activation: Literal["tanh", "relu"] = "tanh"


@dataclass(frozen=True)
class CheckpointConfig:
    """When and what to keep, so a run can resume and its best policy survives."""

    every_updates: int = 100
    keep_last: int = 3
    keep_best: bool = True
    """Also keep the checkpoint with the best evaluation solve rate, beyond the last few."""
    directory: str = "checkpoints"
    """Relative paths are taken inside the run directory."""


@dataclass(frozen=True)
class TrainConfig:
    """One training run: the config `impulse train` resolves and writes as config.toml in its run directory."""

    name: str = "default"
    """Run name; also the run id in bus key expressions of distributed runs."""
    seed: int = 0
    run_dir: str = "runs/{name}"
    """Where checkpoints, logs and the resolved config go; "{name}" is replaced by the run name."""
    total_env_steps: int = 2**30
    env: EnvConfig = field(default_factory=EnvConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)

    def output_dir(self) -> Path:
        """The run directory with the run name filled in."""
        return Path(self.run_dir.replace("{name}", self.name))
