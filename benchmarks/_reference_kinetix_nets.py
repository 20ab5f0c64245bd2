"""Kinetix's own networks and checkpoints, made INSIDE the reference virtualenv, for checking `impulse
import-kinetix` (benchmarks/kinetix_import.py) and for the CI fixture (tests/fixtures/kinetix/).

Like _reference_runner.py, this is the only kind of code that imports Kinetix, it imports nothing from our
project, and every subcommand prints JSON lines on stdout (progress on stderr).

    nets --levels PATH [PATH ...] --out DIR [--variants NAME ...] [--small] [--steps 0,10,40]
        For each network variant (entity transformer, its legacy-entity-id and full-attention forms, the
        permutation-invariant MLP, flat MLPs for each action type, the pixel CNN): build it with Kinetix's
        make_network_from_config, initialise it and perturb every parameter (so biases and gate biases are not
        zero and a mapping that dropped them would show), save it both as Kinetix's training scripts do
        (save_model -> full_model.pbz2) and as its pretrained format (save_pretrained_checkpoint), then play the
        levels with random actions and record, at the given steps, the observation and Kinetix's action
        distribution and value. One JSON line per variant names the files; DIR/<variant>/outputs.npz holds the
        observations (obs_<field>), per-dimension log-probabilities (`log_probs`, [N, sum(nvec)] for
        multi-discrete, [N, 11] for discrete), Gaussian means and log-stds, and values.
    train --level PATH --out DIR [--updates 12] [--num-envs 64] [--num-steps 64]
        PPO on one level with Kinetix's own rollout-and-update function (kinetix.util.learning.
        sample_trajectories_and_learn), network and env (entity transformer, multi-discrete); saves the policy
        with save_model and prints one JSON line per update (solve rate of finished episodes). Kinetix's update
        calls jax.tree.tree_map, gone from our JAX: it is aliased to jax.tree.map first.
    evaluate --level PATH --checkpoint FILE [--episodes 512] [--seed 0]
        Solve rate of a saved policy over independent episodes from the level's start (first episode of each
        environment, sampled actions), played by Kinetix's env and network.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState
from kinetix.environment import make_kinetix_env
from kinetix.environment.spaces import ActionType, ObservationType
from kinetix.environment.wrappers import LogWrapper
from kinetix.models import make_network_from_config
from kinetix.models.actor_critic import ScannedRNN
from kinetix.util.learning import sample_trajectories_and_learn
from kinetix.util.saving import load_from_json_file, load_params, save_model, save_pretrained_checkpoint

sys.path.append(str(Path(__file__).resolve().parent))  # see _reference_common.py
from _reference_common import emit, environment  # noqa: E402

MODEL_DEFAULTS: dict[str, Any] = {
    "actor_width": 128, "critic_width": 128, "actor_depth": 5, "critic_depth": 5, "activation": "tanh",
    "recurrent_model": False, "num_heads": 8, "transformer_depth": 2, "transformer_size": 16,
    "transformer_encoder_size": 128, "aggregate_mode": "dummy_and_mean", "full_attention_mask": False,
    "transformer_ffn": False, "multilayer_joint_thruster_mixing": False, "joint_thruster_block_num_layers": 1,
    "joint_thruster_block_hidden_dim_multiplication": 1, "dropout_prob": 0.0, "symbolic_embedding_dim": 256,
    "encoder_size": 64, "separate_actor_critic": False, "permutation_invariant_mlp": False,
    "legacy_entity_id": False,
}
SMALL = {"actor_width": 8, "critic_width": 8, "actor_depth": 2, "critic_depth": 2, "num_heads": 4,
         "transformer_depth": 2, "transformer_size": 8, "transformer_encoder_size": 12, "symbolic_embedding_dim": 16,
         "encoder_size": 10}

VARIANTS: dict[str, dict[str, Any]] = {
    "transformer": {"observation_type": "symbolic_entity", "action_type": "multi_discrete"},
    "transformer_legacy_id": {"observation_type": "symbolic_entity", "action_type": "multi_discrete",
                              "legacy_entity_id": True},
    "transformer_full_relu": {"observation_type": "symbolic_entity", "action_type": "multi_discrete",
                              "full_attention_mask": True, "activation": "relu"},
    "entity": {"observation_type": "symbolic_entity", "action_type": "multi_discrete",
               "permutation_invariant_mlp": True},
    "flat": {"observation_type": "symbolic_flat", "action_type": "multi_discrete"},
    "flat_discrete": {"observation_type": "symbolic_flat", "action_type": "discrete"},
    "flat_continuous": {"observation_type": "symbolic_flat", "action_type": "continuous"},
    "pixels": {"observation_type": "pixels", "action_type": "multi_discrete", "cnn_mode": "impala_fast"},
}
PERTURBATION = 0.1


def model_config(variant: str, small: bool) -> dict[str, Any]:
    """The JSON-able Kinetix config of a variant: model settings plus observation and action types."""
    return {**MODEL_DEFAULTS, **(SMALL if small else {}), **VARIANTS[variant]}


def build(config: dict[str, Any], env_params: Any, static: Any) -> tuple[Any, Any]:
    """Kinetix's env and network for a JSON-able config (enums filled in as its scripts do)."""
    action = ActionType.from_string(config["action_type"])
    observation = {"symbolic_entity": ObservationType.SYMBOLIC_ENTITY, "symbolic_flat": ObservationType.SYMBOLIC_FLAT,
                   "pixels": ObservationType.PIXELS}[config["observation_type"]]
    env = LogWrapper(make_kinetix_env(action, observation, None, env_params, static))
    full = {**config, "action_type": action, "observation_type": observation,
            "static_env_params": {"num_motor_bindings": static.num_motor_bindings,
                                  "num_thruster_bindings": static.num_thruster_bindings}}
    return env, make_network_from_config(env, env_params, full, network_kws={})


def apply(network: Any, params: Any, obs: Any) -> tuple[Any, Any]:
    """Kinetix's (distribution, value) for a batch of observations [B, ...] (its networks take [T, B, ...])."""
    x = (jax.tree.map(lambda a: a[None], obs), jnp.zeros((1, jax.tree.leaves(obs)[0].shape[0]), bool))
    _, pi, value = network.apply(params, ScannedRNN.initialize_carry(jax.tree.leaves(obs)[0].shape[0]), x)
    return pi, value[0]


def distribution_arrays(pi: Any) -> dict[str, np.ndarray]:
    if hasattr(pi, "distributions"):
        return {"log_probs": np.concatenate([np.asarray(jax.nn.log_softmax(d.logits[0], -1)) for d in pi.distributions],
                                            axis=-1)}
    if hasattr(pi, "logits"):
        return {"log_probs": np.asarray(jax.nn.log_softmax(pi.logits[0], -1))}
    return {"mean": np.asarray(pi.loc[0]), "log_std": np.asarray(jnp.log(pi.scale_diag[0]))}


def collect_observations(env: Any, env_params: Any, levels: list[Any], steps: list[int]) -> Any:
    """Observations of each level at the given step counts, under uniform random actions (fixed keys)."""
    action_space = env.action_space(env_params)
    found = []
    for index, level in enumerate(levels):
        key = jax.random.PRNGKey(index)
        obs, state = env.reset(key, env_params, override_reset_state=level)
        for t in range(max(steps) + 1):
            if t in steps:
                found.append(obs)
            key, action_key, step_key = jax.random.split(key, 3)
            obs, state, _, _, _ = env.step(step_key, state, action_space.sample(action_key), env_params,
                                           override_reset_state=level)
    return jax.tree.map(lambda *xs: jnp.stack(xs), *found)


def nets(args: argparse.Namespace) -> None:
    loaded = [load_from_json_file(str(Path(p).resolve())) for p in args.levels]
    levels = [state for state, _, _ in loaded]
    static, env_params = loaded[0][1], loaded[0][2]
    steps = [int(s) for s in args.steps.split(",")]
    out = Path(args.out)
    for variant in args.variants:
        config = model_config(variant, args.small)
        env, network = build(config, env_params, static)
        obs = collect_observations(env, env_params, levels, steps)
        init_key, noise_key = jax.random.split(jax.random.PRNGKey(args.seed))
        params = {"params": network.init(init_key, ScannedRNN.initialize_carry(1),
                                         (jax.tree.map(lambda a: a[None, :1], obs), jnp.zeros((1, 1), bool)))
                  ["params"]}
        leaves, treedef = jax.tree.flatten(params)
        noise = jax.random.split(noise_key, len(leaves))
        params = jax.tree.unflatten(treedef, [x + PERTURBATION * jax.random.normal(k, x.shape, x.dtype)
                                              for x, k in zip(leaves, noise)])
        pi, value = apply(network, params, obs)
        directory = out / variant
        directory.mkdir(parents=True, exist_ok=True)
        train_state = TrainState.create(apply_fn=network.apply, params=params, tx=optax.adam(1e-4))
        save_config = {"economical_saving": False, "run_name": variant, "random_hash": 0,
                       "save_path": str(directory)}
        with contextlib.redirect_stdout(sys.stderr):
            save_model(train_state, 0, save_config, save_to_wandb=False)
        pbz2 = next(directory.glob("*/full_model.pbz2"))
        pretrained = directory / "pretrained"
        save_pretrained_checkpoint(params, {"model": config, "seed": args.seed}, pretrained)
        fields = ({f.name: getattr(obs, f.name) for f in dataclasses.fields(obs)} if dataclasses.is_dataclass(obs)
                  else {"flat": obs})
        arrays = {f"obs_{k}": np.asarray(v) for k, v in fields.items()}
        arrays.update(distribution_arrays(pi))
        arrays["value"] = np.asarray(value)
        np.savez_compressed(directory / "outputs.npz", **arrays)
        emit({"variant": variant, "small": args.small, "pbz2": str(pbz2), "pretrained": str(pretrained),
              "outputs": str(directory / "outputs.npz"), "observations": int(value.shape[0]),
              "parameters": int(sum(x.size for x in jax.tree.leaves(params))), "model": config,
              "levels": [str(p) for p in args.levels], **environment()})


TRAIN_CONFIG = {"gamma": 0.995, "gae_lambda": 0.9, "clip_eps": 0.2, "ent_coef": 0.01, "vf_coef": 0.5,
                "outer_rollout_steps": 1}


def train(args: argparse.Namespace) -> None:
    if not hasattr(jax.tree, "tree_map"):
        # Kinetix 3.0.2's update calls jax.tree.tree_map, which newer JAX no longer has; it is jax.tree.map.
        jax.tree.tree_map = jax.tree.map
    level, static, env_params = load_from_json_file(str(Path(args.level).resolve()))
    config = model_config("transformer", small=False)
    env, network = build(config, env_params, static)
    key = jax.random.PRNGKey(args.seed)
    key, init_key, reset_key = jax.random.split(key, 3)
    reset = jax.jit(jax.vmap(lambda k: env.reset(k, env_params, override_reset_state=level)))
    obs, env_state = reset(jax.random.split(reset_key, args.num_envs))
    params = network.init(init_key, ScannedRNN.initialize_carry(args.num_envs),
                          (jax.tree.map(lambda a: a[None], obs), jnp.zeros((1, args.num_envs), bool)))
    params = {"params": params["params"]}
    tx = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(args.lr, eps=1e-5))
    train_state = TrainState.create(apply_fn=network.apply, params=params, tx=tx)
    ppo = {**TRAIN_CONFIG, "num_train_envs": args.num_envs, "num_steps": args.num_steps,
           "num_minibatches": args.num_minibatches, "update_epochs": args.epochs}
    hstate = ScannedRNN.initialize_carry(args.num_envs)
    start = time.perf_counter()
    for update in range(args.updates):
        # The function resets finished episodes to the state it starts from, so every rollout starts from the
        # level's start; an episode longer than num_steps is cut there and its value bootstrapped.
        key, reset_key = jax.random.split(key)
        obs, env_state = reset(jax.random.split(reset_key, args.num_envs))
        (key, train_state, _, _, _), rollout = sample_trajectories_and_learn(
            env, env_params, ppo, key, train_state, hstate, obs, env_state)
        info = rollout[6]
        finished = np.asarray(info["returned_episode"])
        solved = np.asarray(info["returned_episode_solved"])
        emit({"update": update + 1, "episodes": int(finished.sum()),
              "solve_rate": float((solved * finished).sum() / max(1, finished.sum())),
              "elapsed_s": time.perf_counter() - start})
    directory = Path(args.out)
    directory.mkdir(parents=True, exist_ok=True)
    with contextlib.redirect_stdout(sys.stderr):
        save_model(train_state, args.updates * args.num_envs * args.num_steps,
                   {"economical_saving": False, "run_name": "trained", "random_hash": 0, "save_path": str(directory)},
                   save_to_wandb=False)
    pbz2 = next(directory.glob("*/full_model.pbz2"))
    (directory / "model.json").write_text(json.dumps({"model": config}))
    emit({"saved": str(pbz2), "env_steps": args.updates * args.num_envs * args.num_steps,
          "train_s": time.perf_counter() - start, **environment()})


def evaluate(args: argparse.Namespace) -> None:
    level, static, env_params = load_from_json_file(str(Path(args.level).resolve()))
    config = model_config("transformer", small=False)
    env, network = build(config, env_params, static)
    params = load_params(args.checkpoint)["params"]
    n = args.episodes

    @jax.jit
    def play(key: jax.Array) -> tuple[jax.Array, jax.Array]:
        reset_key, key = jax.random.split(key)
        obs, state = jax.vmap(lambda k: env.reset(k, env_params, override_reset_state=level))(
            jax.random.split(reset_key, n))

        def step(carry: Any, _: None) -> tuple[Any, tuple[jax.Array, jax.Array]]:
            obs, state, key = carry
            key, action_key, step_key = jax.random.split(key, 3)
            pi, _ = apply(network, params, obs)
            action = pi.sample(seed=action_key)[0]
            obs, state, _, done, info = jax.vmap(
                lambda k, s, a: env.step(k, s, a, env_params, override_reset_state=level))(
                jax.random.split(step_key, n), state, action)
            return (obs, state, key), (done, info["GoalR"] > 0)

        _, (done, solved) = jax.lax.scan(step, (obs, state, key), None, length=int(env_params.max_timesteps))
        first = jnp.cumsum(done, axis=0) - done == 0  # steps up to and including the first episode's end
        return jnp.any(done & first, axis=0), jnp.any(done & solved & first, axis=0)

    start = time.perf_counter()
    finished, solved = play(jax.random.PRNGKey(args.seed))
    emit({"level": str(args.level), "episodes": n, "finished": int(finished.sum()), "solved": int(solved.sum()),
          "solve_rate": float(solved.sum() / n), "seed": args.seed, "eval_s": time.perf_counter() - start,
          **environment()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("nets")
    p.add_argument("--levels", nargs="+", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--small", action="store_true")
    p.add_argument("--steps", default="0,10,40")
    p.add_argument("--seed", type=int, default=0)
    p = commands.add_parser("train")
    p.add_argument("--level", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--updates", type=int, default=12)
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--num-steps", type=int, default=64)
    p.add_argument("--num-minibatches", type=int, default=4)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--seed", type=int, default=0)
    p = commands.add_parser("evaluate")
    p.add_argument("--level", required=True)
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--episodes", type=int, default=512)
    p.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    # Compiling Kinetix's PPO step takes minutes on a CPU: keep compiled programs across runs.
    cache = Path(__file__).resolve().parents[1] / ".cache" / "jax-reference"
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    {"nets": nets, "train": train, "evaluate": evaluate}[args.command](args)


if __name__ == "__main__":
    main()
