"""The learner's configuration sections: `[ppo]`, `[network]`, `[checkpoint]`, `[eval]` and `[learner]`, and
`TrainingSetup`, the sections a training run reads.

Defaults are Kinetix's PPO setup (entity transformer, 2,048 environments, 256-step rollouts), so a run with no
overrides is comparable with the published baselines. These are plain dataclasses; the run configuration that
composes every room's sections, and its TOML/override loader, are `deploy`'s (`deploy.run_config.RunConfig`), so
every field needs a default and a type the loader understands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Protocol

from impulse.curriculum.config import CurriculumConfig
from impulse.engine.config_checks import check_device_list, check_range
from impulse.engine.env.config import EnvConfig


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters, plus the correction for data collected by an older policy (distributed actors)."""

    num_envs: int = 2048
    """Environments stepped side by side per rollout (in fused mode; in each actor, in distributed mode)."""
    num_steps: int = 256
    """Environment steps per rollout, per environment."""
    restart_envs: bool = False
    """Restart every environment on the new level batch at the start of each rollout, as Kinetix's SFL trainer
    does: an episode lasts at most num_steps (the value of its last state stands in for the rest) and every
    level of a batch is played from its start. False: an episode runs across rollouts until it ends or times
    out, and a new batch's levels are taken up as episodes end."""
    num_minibatches: int = 32
    """Minibatches split across environments (whole sequences), so it must divide num_envs."""
    update_epochs: int = 8
    """Passes over each rollout batch per update."""
    learning_rate: float = 1e-4
    """Adam step size (at the start of the run when anneal_lr)."""
    anneal_lr: bool = True
    """Decay the learning rate linearly to zero over the run."""
    gamma: float = 0.995
    """Discount factor."""
    gae_lambda: float = 0.9
    """GAE lambda: how far advantages look ahead before trusting the value estimate."""
    clip_eps: float = 0.2
    """PPO clip range of the probability ratio."""
    ent_coef: float = 0.01
    """Weight of the entropy bonus."""
    vf_coef: float = 0.5
    """Weight of the value loss."""
    max_grad_norm: float = 0.5
    """Gradients are clipped to this global norm."""
    normalize_advantages: bool = True
    """Standardise advantages within each minibatch (Kinetix does)."""
    clip_value: bool = True
    """Clip the value prediction to within clip_eps of the behaviour value, as the policy ratio is clipped."""
    correction: Literal["vtrace", "none"] = "vtrace"
    """How value targets and advantages are estimated. "vtrace": V-trace from the learner's current values, each
    step's trace cut by min(c-bar, pi/mu) for data from a lagging policy; on-policy its targets are GAE's
    lambda-returns, but its advantages (r_t + gamma v_{t+1} - V(x_t), as in IMPALA) are not GAE's. "none": GAE
    from the values the behaviour policy recorded, as plain PPO. Either way the policy loss keeps the importance
    weight `proximal` asks for, so "none" does not drop the correction of the policy gradient."""
    vtrace_rho_bar: float = 1.0
    """V-trace: importance weights in the value targets' TD errors are clipped at this (rho-bar)."""
    vtrace_c_bar: float = 1.0
    """V-trace: trace-cutting weights are clipped at this (c-bar); gae_lambda scales them further. At most
    vtrace_rho_bar; 0 cuts every trace (one-step TD targets)."""
    proximal: Literal["behaviour", "learner"] = "learner"
    """What the PPO clip is centred on. "learner": the learner's policy at the start of the update, with every
    sample weighted by min(vtrace_rho_bar, pi_learner / pi_behaviour), the decoupled objective of Hilton et al.
    (2022), so that a batch from a lagging actor is not clipped for being old. "behaviour": the policy that acted
    (classic PPO: with actors a few versions behind, much of every batch starts outside the clip and teaches
    nothing, which kept distributed runs from learning; benchmarks/RESULTS.md). The two are the same objective
    when the data is on-policy (fused mode), up to rounding."""
    max_policy_lag: int = 4
    """Trajectories older than this many policy versions are dropped rather than corrected; 0 keeps only those
    acted by the learner's current weights."""
    max_non_finite_updates: int = 5
    """An update whose loss, gradients or new parameters hold a NaN or an infinity is skipped (parameters and
    optimiser state stay as they were) and counted (`skipped/non_finite`); after this many in a row the run stops
    with an error naming the likely cause. 0: never stop (every such update is still skipped)."""

    @property
    def steps_per_update(self) -> int:
        """Environment steps in one batch, which is one update: num_envs x num_steps."""
        return self.num_envs * self.num_steps

    def updates_for(self, total_env_steps: int, hosts: int = 1) -> int:
        """Updates a run of `total_env_steps` makes: whole batches, rounded up, at least one. A learner on `hosts`
        processes trains on one batch of each per update (`learner.hosts`)."""
        return max(1, math.ceil(total_env_steps / (self.steps_per_update * hosts)))

    def __post_init__(self) -> None:
        for name in ("num_envs", "num_steps", "num_minibatches", "update_epochs"):
            check_range(f"ppo.{name}", getattr(self, name), at_least=1)
        for name in ("learning_rate", "clip_eps", "max_grad_norm", "vtrace_rho_bar"):
            check_range(f"ppo.{name}", getattr(self, name), above=0)
        for name in ("gamma", "gae_lambda"):
            check_range(f"ppo.{name}", getattr(self, name), at_least=0, at_most=1)
        for name in ("ent_coef", "vf_coef", "vtrace_c_bar", "max_policy_lag", "max_non_finite_updates"):
            check_range(f"ppo.{name}", getattr(self, name), at_least=0)
        if self.num_envs % self.num_minibatches:
            raise ValueError(
                f"num_minibatches ({self.num_minibatches}) must divide num_envs ({self.num_envs}), "
                "because minibatches are whole environment sequences"
            )
        if self.vtrace_c_bar > self.vtrace_rho_bar:
            raise ValueError(
                f"vtrace_c_bar ({self.vtrace_c_bar}) must not exceed vtrace_rho_bar ({self.vtrace_rho_bar})"
            )


@dataclass(frozen=True)
class NetworkConfig:
    """Policy and value network shape (see `learner.networks`). Defaults give Kinetix's model sizes: separate
    actor and critic heads of 5 x Dense(128) tanh over a torso chosen by `kind`."""

    kind: Literal["transformer", "entity", "flat", "cnn"] = "transformer"
    """"transformer": attention over shapes with joint/thruster message passing (entity observation);
    "entity": a cheaper permutation-invariant MLP over the same entity observation; "flat": an MLP over the
    symbolic flat observation vector; "cnn": Kinetix's small CNN over the pixel observation."""
    width: int = 128
    """Units of each Dense layer of the actor and critic heads."""
    depth: int = 5
    """Dense layers in each of the separate actor and critic heads; 0: the heads' outputs read the torso's
    embedding directly."""
    activation: Literal["tanh", "relu"] = "tanh"
    """Nonlinearity of the heads and the entity encoders."""
    transformer_layers: int = 2
    """Attention layers; 0: the embedding is the mean of the encoded shape tokens and the summary token, with no
    attention (joints and thrusters then go unused)."""
    num_heads: int = 8
    """Attention heads per layer; shared out evenly among the 4 attention-mask channels, so a multiple of 4
    unless full_attention_mask."""
    transformer_size: int = 16
    """Query/key/value features per attention head."""
    transformer_encoder_size: int = 128
    """Width of every entity token in the transformer (encoders, attention output, messages)."""
    full_attention_mask: bool = False
    """Every head attends over all active shapes (channel 0), ignoring the joint and contact channels."""
    entity_encoder_size: int = 64
    """Permutation-invariant MLP: per-entity embedding width, of which 4 are the entity-type one-hot."""
    entity_heads: int = 8
    """Entity network: heads of the per-shape encoding, each entity_head_size wide, summed over the shapes."""
    entity_head_size: int = 32
    """Permutation-invariant MLP: per-entity multi-head Dense (heads x size, ReLU), summed over entities."""
    flat_embedding_size: int = 128
    """Flat MLP: width of the ReLU layer between the observation vector and the heads."""
    summary_token: Literal["learned", "ones"] = "learned"
    """Transformer: the extra token that every shape may attend to and that joins the final mean: "learned" (a
    parameter initialised to ones) or "ones" (a constant, as Kinetix's dummy token, for imported Kinetix
    policies that should keep it fixed when fine-tuned)."""
    sublayer_relu: bool = False
    """Transformer: a ReLU on the attention output and on the feed-forward output (in place of `activation`)
    before their gates, as Kinetix's layers have (needed to run Kinetix's weights)."""
    shape_type_column: Literal["none", "type", "zero"] = "none"
    """Transformer: "type" narrows the polygon and circle encoders by one unit and appends a constant type
    column (1 for polygons, 0 for circles), as Kinetix's encoders; "zero" appends 0 for both, which is what the
    networks of the Kinetix paper saw (Kinetix's `legacy_entity_id`)."""
    count_inactive_entities: bool = False
    """Permutation-invariant MLP: inactive slots enter the sum as all-zero entity rows, each adding the ReLU of
    the multi-head layer's bias, as in Kinetix (needed to run its weights), instead of being left out; the
    embedding then depends on the number of slots."""

    def __post_init__(self) -> None:
        for name in ("width", "num_heads", "transformer_size", "entity_heads", "entity_head_size",
                     "flat_embedding_size"):
            check_range(f"network.{name}", getattr(self, name), at_least=1)
        for name in ("depth", "transformer_layers"):
            check_range(f"network.{name}", getattr(self, name), at_least=0)
        # With a type column the polygon and circle encoders are one unit narrower than the token.
        check_range("network.transformer_encoder_size", self.transformer_encoder_size,
                    at_least=1 if self.shape_type_column == "none" else 2)
        if not self.full_attention_mask and self.num_heads % 4:
            raise ValueError(
                f"num_heads ({self.num_heads}) must be a multiple of 4, the attention-mask channels "
                "(or set full_attention_mask)"
            )
        if self.entity_encoder_size <= 4:
            raise ValueError(f"entity_encoder_size ({self.entity_encoder_size}) must exceed the 4-way type one-hot")


@dataclass(frozen=True)
class CheckpointConfig:
    """When and what to keep, so a run can resume and its best policy survives."""

    every_updates: int = 100
    """Checkpoint every this many updates, and once more when the run ends; 0: only when it ends (the curriculum
    service counts result messages instead, saves after every one with 0, and at most once every 10 s)."""
    keep_last: int = 3
    """Newest checkpoints kept (at least 1)."""
    keep_best: bool = True
    """Also keep the checkpoint with the best evaluation solve rate, beyond the last few."""
    directory: str = "checkpoints"
    """Relative paths are taken inside the run directory."""

    def __post_init__(self) -> None:
        check_range("checkpoint.every_updates", self.every_updates, at_least=0)
        check_range("checkpoint.keep_last", self.keep_last, at_least=1)


@dataclass(frozen=True)
class EvalConfig:
    """Evaluation in `impulse train` (every `every_updates` and at the end) and by `impulse eval`."""

    levels: str = ""
    """Level sets to evaluate on, comma-separated (each as env.levels takes it, e.g. "kinetix:s,handmade"); empty:
    the training levels, or the hand-made set when training on random levels."""
    attempts: int = 20
    """Episodes per level, each from the level's start (Kinetix scores hand-made levels over 20); 0 skips the
    evaluation at the end of training."""
    every_updates: int = 0
    """`impulse train` also evaluates the policy every this many updates and writes the scores to metrics.jsonl
    (the columns the evaluator process gives a distributed run); 0: only at the end."""

    def __post_init__(self) -> None:
        check_range("eval.attempts", self.attempts, at_least=0)
        check_range("eval.every_updates", self.every_updates, at_least=0)


@dataclass(frozen=True)
class EvaluatorConfig:
    """The evaluator process of a distributed run: it follows the learner's weights and scores the newest policy
    on level sets, as `impulse eval` does, while the run trains (`learner.evaluator`)."""

    levels: str = ""
    """Level sets to score on, comma-separated (e.g. "kinetix:s,handmade"); empty: no evaluator."""
    every_updates: int = 50
    """Score the newest policy once the learner is this many versions past the last one scored; versions that
    arrive while it scores are skipped (and counted)."""
    attempts: int = 20
    """Episodes per level (Kinetix's protocol: 20)."""
    devices: tuple[int, ...] = ()
    """GPUs the evaluator runs on (positions among those it may see, as actors.devices); empty: the first."""

    def __post_init__(self) -> None:
        check_range("evaluator.every_updates", self.every_updates, at_least=1)
        check_range("evaluator.attempts", self.attempts, at_least=1)
        check_device_list("evaluator.devices", self.devices)


@dataclass(frozen=True)
class RecorderConfig:
    """The recorder process of a distributed run: it hears the actors' trajectories and the levels they played and
    writes whole episodes to an on-disk dataset (`learner.recorder`, `learner.dataset`), for behaviour cloning
    (`impulse train-bc`) and offline analysis."""

    path: str = ""
    """The dataset folder (created, or appended to when it holds a dataset of the same environment); "{run_dir}"
    is replaced by the run directory. Empty: no recorder."""
    shard_steps: int = 16384
    """Steps per shard: episodes are written in shards of about this many steps, each complete on disk or not at
    all."""
    flush_s: float = 60.0
    """Write the episodes waiting for a shard at least this often, however few they are (a kill loses at most
    this much)."""
    max_gigabytes: float = 20.0
    """Disk the dataset may use; when a shard would pass it, `when_full` says what happens."""
    when_full: Literal["stop", "drop_oldest"] = "stop"
    """"stop": record nothing more (said on the status line and counted); "drop_oldest": delete the oldest shards
    to make room."""

    def __post_init__(self) -> None:
        check_range("recorder.shard_steps", self.shard_steps, at_least=1)
        check_range("recorder.flush_s", self.flush_s, at_least=0)
        check_range("recorder.max_gigabytes", self.max_gigabytes, at_least=0)


@dataclass(frozen=True)
class BCConfig:
    """Behaviour cloning (`impulse train-bc`): the policy learns to choose the actions of a recorded dataset."""

    epochs: int = 20
    """Passes over the selected steps."""
    batch_size: int = 1024
    """Steps per gradient step."""
    learning_rate: float = 3e-4
    """Adam step size."""
    solved_only: bool = True
    """Learn only from episodes that ended solved."""
    min_return: float = -1e9
    """... and only from episodes whose return is at least this."""
    validation_fraction: float = 0.1
    """Episodes held out to measure the loss on data not trained on (chosen by the seed)."""

    def __post_init__(self) -> None:
        check_range("bc.epochs", self.epochs, at_least=1)
        check_range("bc.batch_size", self.batch_size, at_least=1)
        check_range("bc.learning_rate", self.learning_rate, above=0)
        check_range("bc.validation_fraction", self.validation_fraction, at_least=0, below=1)


@dataclass(frozen=True)
class LearnerConfig:
    """The learner service of a distributed run."""

    publish_every: int = 1
    """Publish the weights every this many updates."""
    slow_down_s: float = 0.0
    """Sleep this long after every update: simulates a slow learner (back-pressure tests and experiments); 0: no
    sleep."""
    devices: tuple[int, ...] = ()
    """GPUs the PPO update is sharded over, data parallel (`learner.sharding`), as positions among the GPUs the
    process may see; the learner sees only these. Empty: the first device only. On a machine without GPUs, the
    first len(devices) devices (several only when XLA simulates them)."""
    hosts: int = 1
    """Learner processes, one per host, the PPO update is data parallel over (`learner.hosts`): each trains on its
    share of the actors' batches, the gradients are summed across them, and the parameters stay identical. Each
    process is started with its own `--host-index` (0, the leader, speaks for the group); 1: one process."""
    coordinator: str = ""
    """host:port where the leader (`--host-index 0`) listens for the other learner processes when learner.hosts >
    1; every learner process must reach it."""

    def __post_init__(self) -> None:
        check_device_list("learner.devices", self.devices)
        check_range("learner.hosts", self.hosts, at_least=1)
        check_range("learner.publish_every", self.publish_every, at_least=1)
        check_range("learner.slow_down_s", self.slow_down_s, at_least=0)


class TrainingSetup(Protocol):
    """The sections a training run reads (the fused trainer, the final evaluation, `impulse eval`); the run
    configuration (`deploy.run_config.RunConfig`) has them all, and nothing else in the learner needs more."""

    @property
    def seed(self) -> int: ...

    @property
    def total_env_steps(self) -> int: ...

    @property
    def env(self) -> EnvConfig: ...

    @property
    def ppo(self) -> PPOConfig: ...

    @property
    def network(self) -> NetworkConfig: ...

    @property
    def checkpoint(self) -> CheckpointConfig: ...

    @property
    def eval(self) -> EvalConfig: ...

    @property
    def curriculum(self) -> CurriculumConfig: ...
