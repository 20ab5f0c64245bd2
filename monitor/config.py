"""The `[monitor]` section: what the processes of a run stream to the Rerun viewer (docs/monitoring.md), and where
its metrics go besides `metrics.jsonl` (TensorBoard, W&B: docs/metrics.md)."""

from __future__ import annotations

from dataclasses import dataclass

from impulse.engine.config_checks import check_range


@dataclass(frozen=True)
class MonitorConfig:
    """Live monitoring in Rerun (docs/monitoring.md): what the processes of a distributed run stream to the
    viewer that `impulse view` hosts. `impulse launch --view` turns it on and starts the viewer."""

    enabled: bool = False
    """Stream rollouts, curves and the curriculum to the Rerun server at `url`; off, no Rerun code runs."""
    url: str = "rerun+http://127.0.0.1:9876/proxy"
    """The Rerun gRPC server the processes log to (`impulse view` hosts it on this port)."""
    watch_envs: int = 1
    """Environments each actor streams (its first ones); 0 streams curves only."""
    frames_per_s: float = 30.0
    """Most frames per second an actor streams; it streams whole rollouts, skipping rollouts to keep to this."""
    contacts: bool = False
    """Also draw where shapes touch in streamed rollouts (found again on the logging thread)."""
    queue_rollouts: int = 2
    """Rollouts waiting for the logging thread; one more is dropped (and counted), never waited for."""
    curriculum_every_s: float = 10.0
    """How often the curriculum service logs its histograms, statistics and gallery of top levels."""
    gallery: int = 6
    """Top levels by score drawn in the curriculum gallery; 0: no gallery."""
    server_memory_limit: str = "1GiB"
    """What the viewer's server keeps for late viewers; the oldest data goes first (`rerun --server-memory-limit`)."""
    viewer_memory_limit: str = "2GiB"
    """The native viewer's store; it forgets the oldest data beyond this (`rerun --memory-limit`)."""
    web_port: int = 9090
    """Port of the web viewer `impulse view` serves on a machine without a display."""
    tensorboard: bool = True
    """Also write each metrics.jsonl row as TensorBoard scalars under RUN_DIR/tensorboard/ (step: env_steps)."""
    wandb_project: str = ""
    """Also log each metrics.jsonl row to this Weights & Biases project (step: env_steps); empty: no W&B. Needs
    `pip install 'impulse[wandb]'`."""
    wandb_entity: str = ""
    """The W&B team or user the project belongs to; empty: the logged-in user's default entity."""

    def __post_init__(self) -> None:
        if not (self.url.startswith("rerun") and self.url.endswith("/proxy")):
            raise ValueError(f"monitor.url must look like rerun+http://HOST:PORT/proxy, got {self.url!r}")
        check_range("monitor.watch_envs", self.watch_envs, at_least=0)
        check_range("monitor.frames_per_s", self.frames_per_s, above=0)
        check_range("monitor.queue_rollouts", self.queue_rollouts, at_least=1)
        check_range("monitor.curriculum_every_s", self.curriculum_every_s, above=0)
        check_range("monitor.gallery", self.gallery, at_least=0)
        check_range("monitor.web_port", self.web_port, at_least=1, at_most=65535)
