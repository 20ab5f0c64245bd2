"""Config loading: defaults, TOML files, dotted overrides, type checks and the errors a user sees."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from impulse.deploy.config import ConfigError, config_to_toml, resolve_config, write_resolved_config
from impulse.deploy.run_config import RunConfig
from impulse.engine.env.config import EnvConfig
from impulse.learner.config import PPOConfig
from tests.support.paths import REPO


@dataclass(frozen=True)
class Inner:
    rate: float = 0.5
    mode: Literal["fast", "slow"] = "fast"


@dataclass(frozen=True)
class Outer:
    """Covers the field types the real configs do not use yet."""

    count: int = 1
    label: str = "a"
    sizes: tuple[int, ...] = (1, 2)
    pair: tuple[str, float] = ("x", 1.0)
    names: list[str] = field(default_factory=list)
    limit: int | None = None
    maybe: Inner | None = None
    inner: Inner = field(default_factory=lambda: Inner(rate=0.25))


def test_defaults_are_kinetix_ppo() -> None:
    config = resolve_config(RunConfig, None, [])
    assert config == RunConfig()
    assert config.ppo.num_envs == 2048 and config.ppo.num_steps == 256
    assert config.ppo.learning_rate == 1e-4 and config.ppo.anneal_lr
    assert (config.ppo.gamma, config.ppo.gae_lambda, config.ppo.clip_eps) == (0.995, 0.9, 0.2)
    assert config.ppo.correction == "vtrace"
    assert config.env == EnvConfig(size="s", levels="handmade", frame_skip=2, max_timesteps=256)
    assert config.network.width == 128 and config.network.activation == "tanh"
    assert config.checkpoint.keep_last == 3
    assert config.output_dir() == Path("runs/default")


def test_toml_file_then_overrides(tmp_path: Path) -> None:
    path = tmp_path / "run.toml"
    path.write_text('name = "big"\nseed = 3\n[ppo]\nnum_envs = 4096\ngamma = 0.99\n[env]\nsize = "l"\n')
    config = resolve_config(RunConfig, path, ["ppo.gamma=0.9"])
    assert (config.name, config.seed, config.env.size) == ("big", 3, "l")
    assert config.ppo.num_envs == 4096
    assert config.ppo.gamma == 0.9  # the command line wins over the file
    assert config.ppo.learning_rate == PPOConfig().learning_rate  # untouched keys keep their defaults
    assert config.output_dir() == Path("runs/big")


def test_dotted_overrides_coerce_types() -> None:
    config = resolve_config(
        RunConfig, None,
        ["ppo.learning_rate=3e-4", "env.size=m", "ppo.anneal_lr=false", "ppo.clip_eps=1",
         "total_env_steps=1e9", "name=123", "env.levels=\"random\""],
    )
    assert config.ppo.learning_rate == 3e-4
    assert config.env.size == "m"
    assert config.ppo.anneal_lr is False
    assert config.ppo.clip_eps == 1.0 and isinstance(config.ppo.clip_eps, float)
    assert config.total_env_steps == 10**9 and isinstance(config.total_env_steps, int)
    assert config.name == "123"  # a str field takes the text as typed
    assert config.env.levels == "random"


def test_generic_types() -> None:
    config = resolve_config(
        Outer, None,
        ["sizes=[3, 4, 5]", "pair=['y', 2]", "names=[\"p\", \"q\"]", "limit=7", "maybe.mode=slow",
         "inner.mode=slow"],
    )
    assert config.sizes == (3, 4, 5)
    assert config.pair == ("y", 2.0)
    assert config.names == ["p", "q"]
    assert config.limit == 7
    assert config.maybe == Inner(mode="slow")
    assert config.inner == Inner(rate=0.25, mode="slow")  # the field's own default is the base, not Inner()
    assert resolve_config(Outer, None, ["limit=7", "limit=none"]).limit is None


def test_inline_table_override() -> None:
    config = resolve_config(RunConfig, None, ["ppo={gamma = 0.5, num_steps = 64}"])
    assert (config.ppo.gamma, config.ppo.num_steps) == (0.5, 64)


def test_unknown_key_suggests_close_match() -> None:
    with pytest.raises(ConfigError) as info:
        resolve_config(RunConfig, None, ["ppo.learning_rat=1"])
    message = str(info.value)
    assert "unknown config key 'ppo.learning_rat'" in message
    assert "did you mean 'ppo.learning_rate'" in message


def test_key_in_wrong_section_suggests_full_path(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"'gamma'.*did you mean 'ppo\.gamma'"):
        resolve_config(RunConfig, None, ["gamma=0.9"])
    path = tmp_path / "bad.toml"
    path.write_text("[env]\nsise = 'm'\n")
    with pytest.raises(ConfigError, match=r"'env\.sise' \(from .*bad\.toml\); did you mean 'env\.size'"):
        resolve_config(RunConfig, path, [])


def test_unknown_key_without_match_lists_valid_keys() -> None:
    with pytest.raises(ConfigError, match=r"unknown config key 'network\.zzz'.*valid keys in \[network\]: kind"):
        resolve_config(RunConfig, None, ["network.zzz=1"])
    with pytest.raises(ConfigError, match=r"'seed' is a value, not a table"):
        resolve_config(RunConfig, None, ["seed.x=1"])


def test_wrong_type_names_key_type_and_value() -> None:
    with pytest.raises(ConfigError) as info:
        resolve_config(RunConfig, None, ["ppo.num_envs=many"])
    assert str(info.value) == (
        "config key 'ppo.num_envs' expects int, got 'many' (from override 'ppo.num_envs=many')"
    )
    with pytest.raises(ConfigError, match=r"'ppo\.num_steps' expects int, got 2\.5"):
        resolve_config(RunConfig, None, ["ppo.num_steps=2.5"])
    with pytest.raises(ConfigError, match=r"'ppo\.anneal_lr' expects bool, got 1"):
        resolve_config(RunConfig, None, ["ppo.anneal_lr=1"])
    with pytest.raises(ConfigError, match=r"'env\.size' expects one of 's', 'm', 'l', got 'xl'.*did you mean"):
        resolve_config(RunConfig, None, ["env.size=xl"])
    with pytest.raises(ConfigError, match=r"'sizes' expects tuple\[int, \.\.\.\], got \[1, 'a'\]"):
        resolve_config(Outer, None, ["sizes=[1, 'a']"])
    with pytest.raises(ConfigError, match=r"'ppo' expects a table of PPOConfig keys"):
        resolve_config(RunConfig, None, ["ppo=3"])


def test_cross_field_check_becomes_config_error() -> None:
    with pytest.raises(ConfigError, match=r"invalid config \[ppo\]: num_minibatches \(7\) must divide"):
        resolve_config(RunConfig, None, ["ppo.num_minibatches=7"])


def test_a_moved_key_is_read_under_its_old_name_with_a_warning(tmp_path: Path, caplog) -> None:
    """`RunConfig.MOVED_KEYS`: a config.toml written before a key moved, or an old habit on the command line, still
    works, and says the new name; the same key under both names is refused."""
    old = tmp_path / "old.toml"
    old.write_text("[actors]\nnum_actors = 3\nstatus_every_s = 2.5\n")
    with caplog.at_level("WARNING", logger="impulse.config"):
        config = resolve_config(RunConfig, old, ["actors.wire_compact=true"])
    assert (config.bus.status_every_s, config.bus.wire_compact, config.actors.num_actors) == (2.5, True, 3)
    said = caplog.text
    assert "'actors.status_every_s'" in said and "is now 'bus.status_every_s'" in said
    assert "'actors.wire_compact'" in said and "is now 'bus.wire_compact'" in said
    both = tmp_path / "both.toml"
    both.write_text("[actors]\nstatus_every_s = 2.5\n[bus]\nstatus_every_s = 1.0\n")
    with pytest.raises(ConfigError, match="is now 'bus.status_every_s', which is set too"):
        resolve_config(RunConfig, both)


def test_a_curriculum_needs_random_levels() -> None:
    with pytest.raises(ConfigError, match="curriculum.method=plr needs env.levels=random"):
        resolve_config(RunConfig, None, ["curriculum=plr", "env.levels=handmade"])
    assert resolve_config(RunConfig, None, ["curriculum=plr", "env.levels=random"]).curriculum.method == "plr"


def test_lockstep_is_refused_where_it_could_not_take_turns() -> None:
    resolve_config(RunConfig, None, ["actors.lockstep=true", "actors.num_actors=1"])
    with pytest.raises(ConfigError, match=r"actors\.lockstep takes turns with one actor, not 2"):
        resolve_config(RunConfig, None, ["actors.lockstep=true", "actors.num_actors=2"])
    with pytest.raises(ConfigError, match=r"set learner\.publish_every=1 \(it is 3\)"):
        resolve_config(RunConfig, None, ["actors.lockstep=true", "actors.num_actors=1", "learner.publish_every=3"])


# (key, a refused value): counts, sizes, rates and probabilities outside the range the code can use.
OUT_OF_RANGE = [
    ("total_env_steps", "0"),
    ("env.frame_skip", "0"),
    ("env.max_timesteps", "0"),
    ("env.pixel_downscale", "0"),
    ("env.pixel_downscale", "3"),  # must divide the 500-pixel screen
    ("env.dense_reward_scale", "-0.1"),
    ("ppo.num_envs", "0"),
    ("ppo.num_steps", "0"),
    ("ppo.num_minibatches", "0"),
    ("ppo.update_epochs", "0"),
    ("ppo.learning_rate", "0"),
    ("ppo.gamma", "1.01"),
    ("ppo.gamma", "-0.1"),
    ("ppo.gae_lambda", "1.5"),
    ("ppo.clip_eps", "0"),
    ("ppo.ent_coef", "-0.01"),
    ("ppo.vf_coef", "-0.5"),
    ("ppo.max_grad_norm", "0"),
    ("ppo.vtrace_rho_bar", "0"),
    ("ppo.vtrace_c_bar", "-1"),
    ("ppo.max_policy_lag", "-1"),
    ("network.width", "0"),
    ("network.depth", "-1"),
    ("network.transformer_layers", "-1"),
    ("network.num_heads", "0"),  # a multiple of 4, but no heads
    ("network.transformer_size", "0"),
    ("network.transformer_encoder_size", "0"),
    ("network.entity_heads", "0"),
    ("network.entity_head_size", "0"),
    ("network.flat_embedding_size", "0"),
    ("checkpoint.every_updates", "-1"),
    ("checkpoint.keep_last", "0"),
    ("eval.attempts", "-1"),
    ("curriculum.buffer_size", "0"),
    ("curriculum.staging_factor", "1"),
    ("curriculum.max_edits", "-1"),
    ("curriculum.filter_ratio", "0"),
    ("curriculum.filter_steps", "0"),
    ("curriculum.temperature", "0"),
    ("curriculum.staleness_coef", "1.5"),
    ("curriculum.replay_prob", "-0.1"),
    ("curriculum.min_fill", "2"),
    ("curriculum.sfl_ratio", "1.1"),
    ("curriculum.score_memory", "-1"),
    ("curriculum.num_edits", "9"),  # beyond max_edits
    ("curriculum.candidate_episodes", "0"),
    ("curriculum.sfl_score_block", "0"),
    ("actors.num_actors", "0"),
    ("actors.credits", "0"),
    ("actors.credit_timeout_s", "0"),
    ("actors.memory_fraction", "1"),
    ("bus.status_every_s", "-1"),
    ("learner.publish_every", "0"),
    ("learner.slow_down_s", "-1"),
    ("bus.shm_pool_mib", "0"),
    ("bus.lease_ms", "0"),
    ("bus.block_timeout_ms", "-1"),
    ("bus.query_timeout_s", "0"),
    ("monitor.watch_envs", "-1"),
    ("monitor.frames_per_s", "0"),
    ("monitor.queue_rollouts", "0"),
    ("monitor.curriculum_every_s", "0"),
    ("monitor.gallery", "-1"),
    ("monitor.web_port", "0"),
    ("monitor.web_port", "65536"),
]


@pytest.mark.parametrize(("key", "bad"), OUT_OF_RANGE)
def test_out_of_range_value_is_refused_naming_the_dotted_key(key: str, bad: str) -> None:
    with pytest.raises(ConfigError, match=r"invalid config \[") as info:
        resolve_config(RunConfig, None, [f"{key}={bad}"])
    assert f"{key} must be" in str(info.value)


@pytest.mark.parametrize("assignment", ["ppo.learning_rate=nan", "ppo.learning_rate=inf", "bc.min_return=nan",
                                        "curriculum.replay_prob=-inf", "ppo.max_grad_norm=-nan"])
def test_a_float_key_refuses_nan_and_infinities(assignment: str) -> None:
    """No setting means NaN or an infinity (`inf` passes a `> 0` range check, `nan` passes none)."""
    key = assignment.split("=")[0]
    with pytest.raises(ConfigError, match=rf"config key '{key}' expects a finite float, got -?(nan|inf)"):
        resolve_config(RunConfig, None, [assignment])
    assert resolve_config(RunConfig, None, ["ppo.learning_rate=1e38"]).ppo.learning_rate == 1e38


def test_a_score_block_smaller_than_the_candidates_must_divide_them() -> None:
    with pytest.raises(ConfigError, match=r"curriculum.sfl_score_block must divide curriculum.sfl_candidates \(2048\)"):
        resolve_config(RunConfig, None, ["curriculum.sfl_candidates=2048", "curriculum.sfl_score_block=1000"])
    for block in ("512", "2048", "5000"):  # a divisor, all of them, more than all of them: one block
        resolve_config(RunConfig, None, ["curriculum.sfl_candidates=2048", f"curriculum.sfl_score_block={block}"])


def test_range_message_states_the_rule() -> None:
    with pytest.raises(ConfigError) as info:
        resolve_config(RunConfig, None, ["checkpoint.keep_last=0"])
    assert str(info.value) == "invalid config [checkpoint]: checkpoint.keep_last must be >= 1, got 0"
    with pytest.raises(ConfigError, match=r"ppo\.gamma must be in \[0, 1\], got 1\.5"):
        resolve_config(RunConfig, None, ["ppo.gamma=1.5"])
    with pytest.raises(ConfigError, match=r"actors\.memory_fraction must be in \[0, 1\), got 1\.0"):
        resolve_config(RunConfig, None, ["actors.memory_fraction=1"])


@pytest.mark.parametrize("override", [
    "checkpoint.every_updates=0",  # only the checkpoint at the end
    "eval.attempts=0",  # no evaluation at the end of training
    "env.dense_reward_scale=0",  # sparse reward only
    "ppo.max_policy_lag=0",  # on-policy batches only
    "ppo.vtrace_c_bar=0",  # one-step TD targets
    "ppo.ent_coef=0",
    "ppo.gamma=1",
    "network.depth=0",  # linear heads over the torso's embedding
    "network.transformer_layers=0",  # mean of the encoded tokens
    "actors.memory_fraction=0",  # JAX's default
    "bus.status_every_s=0",
    "monitor.watch_envs=0",  # curves only
    "monitor.gallery=0",
    "curriculum={max_edits = 0, num_edits = 0}",  # ACCEL without edits
])
def test_documented_zero_and_edge_values_are_accepted(override: str) -> None:
    resolve_config(RunConfig, None, [override])


def test_type_column_needs_a_token_wider_than_one() -> None:
    resolve_config(RunConfig, None, ["network.transformer_encoder_size=1"])
    with pytest.raises(ConfigError, match=r"network\.transformer_encoder_size must be >= 2, got 1"):
        resolve_config(RunConfig, None, ["network.transformer_encoder_size=1", "network.shape_type_column=type"])


@pytest.mark.parametrize("path", sorted((REPO / "configs").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_configs_load(path: Path) -> None:
    config = resolve_config(RunConfig, path, [])
    assert config.name == path.stem


def test_malformed_inputs(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not of the form key=value"):
        resolve_config(RunConfig, None, ["seed"])
    with pytest.raises(ConfigError, match="config file not found"):
        resolve_config(RunConfig, tmp_path / "missing.toml", [])
    bad = tmp_path / "bad.toml"
    bad.write_text("seed = = 1\n")
    with pytest.raises(ConfigError, match="invalid TOML"):
        resolve_config(RunConfig, bad, [])


def test_resolved_config_round_trips(tmp_path: Path) -> None:
    config = resolve_config(RunConfig, None, ["ppo.gamma=0.9", "env.size=l", "seed=5"])
    path = write_resolved_config(config, tmp_path / "runs" / "x")
    assert path == tmp_path / "runs" / "x" / "config.toml"
    assert resolve_config(RunConfig, path, []) == config
    assert "[ppo]" in config_to_toml(config)

    odd = resolve_config(Outer, None, ["maybe.rate=2", "sizes=[]"])
    odd_path = write_resolved_config(odd, tmp_path)
    assert 'limit = "none"' in odd_path.read_text()
    assert resolve_config(Outer, odd_path, []) == odd


@pytest.mark.parametrize("hub", ["tcp/0.0.0.0:7447", "tcp/10.0.0.5:7447", "tls/hostA.example.org:7447"])
def test_the_open_hub_listens_on_loopback_only(hub: str) -> None:
    with pytest.raises(ConfigError, match="not a loopback address"):
        resolve_config(RunConfig, overrides=[f"bus.hub={hub}"])
    assert resolve_config(RunConfig, overrides=["bus.hub=tcp/[::1]:7447"]).bus.hub == "tcp/[::1]:7447"
