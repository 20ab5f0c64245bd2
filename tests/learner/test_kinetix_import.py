"""Importing Kinetix checkpoints: small networks saved by Kinetix's own code (tests/fixtures/kinetix, see its
README) give, once imported, the action distributions and values Kinetix computed for the same observations;
what cannot be reproduced is refused with a reason; pickles cannot run code; the command writes a run directory
whose checkpoint holds the imported parameters."""

from __future__ import annotations

import bz2
import dataclasses
import json
import os
import pickle
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.env.actions import action_space
from impulse.engine.env.config import EnvConfig
from impulse.engine.env.observation_types import EntityObservation, PixelObservation
from impulse.engine.env.spec import env_from_config
from impulse.learner.distributions import distribution_for
from impulse.learner.kinetix_import import (
    KinetixCheckpoint,
    KinetixImportError,
    check_against,
    import_kinetix,
    policy_outputs,
    read_kinetix_checkpoint,
    read_pickle,
)
from impulse.learner.networks import make_network
from tests.support.paths import FIXTURES as TEST_FIXTURES
from tests.support.paths import REPO

FIXTURES = TEST_FIXTURES / "kinetix"
TOLERANCE = 1e-5
# variant -> Kinetix settings the checkpoint file does not record (the .pbz2 files carry parameters only)
VARIANTS = {
    "transformer": {},
    "transformer_legacy_id": {"legacy_entity_id": True},
    "transformer_full_relu": {"full_attention_mask": True, "activation": "relu"},
    "entity": {"permutation_invariant_mlp": True},
    "flat": {},
    "flat_discrete": {},
    "flat_continuous": {},
    "pixels": {},
}


def fixture_observation(outputs: dict[str, np.ndarray]) -> EntityObservation | PixelObservation | jax.Array:
    if "obs_flat" in outputs:
        return jnp.asarray(outputs["obs_flat"])
    if "obs_image" in outputs:
        return PixelObservation(image=jnp.asarray(outputs["obs_image"]),
                                global_info=jnp.asarray(outputs["obs_global_info"]))
    return EntityObservation(**{f.name: jnp.asarray(outputs[f"obs_{f.name}"])
                                for f in dataclasses.fields(EntityObservation)})


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_imported_network_matches_kinetix(variant):
    outputs = dict(np.load(FIXTURES / variant / "outputs.npz"))
    checkpoint = read_kinetix_checkpoint(FIXTURES / variant)
    imported = import_kinetix(checkpoint, VARIANTS[variant])
    distribution, value = policy_outputs(imported, fixture_observation(outputs))
    expected = (np.concatenate([outputs["mean"], np.broadcast_to(outputs["log_std"], outputs["mean"].shape)], -1)
                if "mean" in outputs else outputs["log_probs"])
    assert distribution.shape == expected.shape
    np.testing.assert_allclose(distribution, expected, atol=TOLERANCE, rtol=0)
    np.testing.assert_allclose(value, outputs["value"], atol=TOLERANCE, rtol=0)
    assert np.abs(outputs["value"]).max() > 0.05  # the comparison is not between two near-zero outputs


def test_settings_a_pbz2_does_not_record_change_the_outputs():
    """Kinetix's defaults are no stand-in for the legacy entity id: imported without it, outputs differ."""
    outputs = dict(np.load(FIXTURES / "transformer_legacy_id" / "outputs.npz"))
    imported = import_kinetix(read_kinetix_checkpoint(FIXTURES / "transformer_legacy_id"))
    assert imported.settings["legacy_entity_id"] == {"value": False, "from": "Kinetix default"}
    distribution, _ = policy_outputs(imported, fixture_observation(outputs))
    assert np.abs(distribution - outputs["log_probs"]).max() > 1e-3


def test_formats_and_inferred_settings():
    pretrained = read_kinetix_checkpoint(FIXTURES / "transformer")
    assert pretrained.options["transformer_encoder_size"] == 12 and not pretrained.unread_classes
    pickled = read_kinetix_checkpoint(FIXTURES / "entity" / "full_model.pbz2")
    assert any("optax" in name for name in pickled.unread_classes)  # the optimiser state stays unread
    imported = import_kinetix(pretrained)
    net = imported.network
    assert (net.kind, net.summary_token, net.sublayer_relu, net.shape_type_column) == ("transformer", "ones",
                                                                                       True, "type")
    assert (net.num_heads, net.transformer_size, net.transformer_encoder_size, net.width, net.depth) == (4, 2, 12, 8,
                                                                                                         2)
    flat = import_kinetix(read_kinetix_checkpoint(FIXTURES / "flat_continuous"))
    assert (flat.network.kind, flat.action, flat.size) == ("flat", "continuous", "s")


def test_settings_from_a_kinetix_run_config_yaml(tmp_path):
    """The config.yaml a Kinetix run writes (sections, older fc_layer_* names) supplies a .pbz2's settings."""
    config = tmp_path / "config.yaml"
    config.write_text("env:\n  observation_type: symbolic_entity\nmodel:\n  fc_layer_depth: 2\n"
                      "  legacy_entity_id: true\n  activation: tanh\n")
    checkpoint = read_kinetix_checkpoint(FIXTURES / "transformer_legacy_id", config)
    assert checkpoint.options["legacy_entity_id"] is True and checkpoint.options["actor_depth"] == 2
    imported = import_kinetix(checkpoint)
    assert imported.network.shape_type_column == "zero"
    assert imported.settings["legacy_entity_id"]["from"] == "checkpoint/options"


def _edited(variant: str, add: dict[tuple[str, ...], np.ndarray] | None = None,
            drop: tuple[str, ...] = ()) -> KinetixCheckpoint:
    checkpoint = read_kinetix_checkpoint(FIXTURES / variant)
    params = {k: v for k, v in checkpoint.params.items() if not any(k[:len(d)] == d for d in [drop] if d)}
    params.update(add or {})
    return dataclasses.replace(checkpoint, params=params)


def _heads_key(*rest: str) -> tuple[str, ...]:
    return ("GeneralActorCriticRNN_0", *rest)


@pytest.mark.parametrize(
    "variant, edit, options, message",
    [
        ("flat", {_heads_key("ScannedRNN_0", "GRUCell_0", "ir", "kernel"): np.zeros((8, 8))}, {}, "recurrent"),
        ("flat", None, {"recurrent_model": True}, "recurrent"),
        ("transformer", None, {"aggregate_mode": "dummy"}, "aggregate_mode"),
        ("transformer", {("Transformer_0", "tf_layers_0", "dense2", "kernel"): np.zeros((48, 12))}, {},
         "transformer_ffn"),
        ("transformer", {("Transformer_0", "joint_layers_0", "Dense_0", "kernel"): np.zeros((36, 12))}, {},
         "multilayer_joint_thruster_mixing"),
        ("entity", {("MultiHeadDense_1", "dense_kernels"): np.zeros((4, 10, 4))}, {}, "separate_actor_critic"),
        ("flat", None, {"actor_depth": 1, "critic_depth": 3}, "depth"),
        ("flat", {_heads_key("DenseAndActivation_1", "Dense_0", "kernel"): np.zeros((8, 5))}, {}, "widths"),
        ("flat", {_heads_key("Dense_2", "kernel"): np.zeros((8, 3))}, {}, "hybrid"),
        ("flat", None, {"observation_type": "pixels"}, "observation_type=pixels"),
        ("flat", None, {"action_type": "discrete"}, "action_type=discrete"),
        ("flat", {_heads_key("Dense_0", "kernel"): np.zeros((8, 7)), _heads_key("Dense_0", "bias"): np.zeros(7)}, {},
         "7 outputs"),
        ("flat", {("Dense_0", "kernel"): np.zeros((100, 8))}, {}, "100 features"),
        ("flat", None, {"activation": "gelu"}, "activation"),
        ("pixels", {("Conv_0", "kernel"): np.zeros((7, 7, 3, 64))}, {}, "resnet_18"),
        ("pixels", None, {"cnn_mode": "resnet_18"}, "cnn_mode=resnet_18"),
        ("pixels", {_heads_key("DenseAndActivation_0", "Dense_0", "kernel"): np.zeros((1000, 8))}, {},
         "1000 features, which matches no pixel downscale"),
        ("flat", None, {"observation_type": "symbolic_flat_padded"}, "observation_type=symbolic_flat_padded"),
        ("transformer", None, {"num_heads": 8}, "num_heads=8"),
        ("entity", None, {"encoder_size": 64}, "encoder_size=64"),
        ("flat", None, {"actor_width": 128}, "another run"),
    ],
)
def test_unrepresentable_networks_are_refused(variant, edit, options, message):
    with pytest.raises(KinetixImportError, match=message):
        import_kinetix(_edited(variant, edit), options)


def test_observation_normalisation_is_refused_unless_waived():
    checkpoint = dataclasses.replace(read_kinetix_checkpoint(FIXTURES / "flat"),
                                     unread_classes={"kinetix.util.learning.RunningMeanStandard"})
    with pytest.raises(KinetixImportError, match="observation-normalisation"):
        import_kinetix(checkpoint)
    assert import_kinetix(checkpoint, {"ignore_observation_normalisation": True}).network.kind == "flat"


def test_tree_that_does_not_fit_the_network_is_refused():
    imported = import_kinetix(read_kinetix_checkpoint(FIXTURES / "flat"))
    heads = imported.params["params"]["heads"]
    heads["critic_out"]["kernel"] = heads["critic_out"]["kernel"][:4]
    spec, _ = env_from_config(EnvConfig(observation="symbolic"))
    network = make_network(imported.network, distribution_for(action_space(spec)))
    template = jax.eval_shape(network.init, jax.random.key(0), jnp.zeros((1, 140)))
    with pytest.raises(KinetixImportError, match="critic_out"):
        check_against(imported, template)


@dataclasses.dataclass
class _Payload:
    marker: Path

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_pickles_cannot_run_code(tmp_path):
    marker = tmp_path / "ran"
    payload = {"params": {"params": {"Dense_0": {"kernel": np.ones((2, 2), np.float32)}}}, "extra": _Payload(marker)}
    path = tmp_path / "full_model.pbz2"
    with bz2.open(path, "wb") as f:
        pickle.dump(payload, f)
    obj, unread = read_pickle(path)
    assert not marker.exists()
    assert any(name.endswith(".system") for name in unread)
    np.testing.assert_array_equal(obj["params"]["params"]["Dense_0"]["kernel"], np.ones((2, 2)))


@pytest.mark.heavy  # a CLI process of its own
def test_command_writes_a_run_directory_with_the_imported_parameters(tmp_path):
    from impulse.deploy.cli import main
    from impulse.deploy.config import resolve_config
    from impulse.deploy.run_config import RunConfig
    from impulse.learner.checkpoint import TRAIN, Checkpointer
    from impulse.learner.run import FusedRun, build

    out = tmp_path / "run"
    level = REPO / "engine" / "levels" / "handmade" / "s_lander.json"
    assert main(["import-kinetix", str(FIXTURES / "flat"), "--out", str(out), "ppo.num_envs=8",
                 "ppo.num_minibatches=2", "ppo.num_steps=8", f"env.levels={level}"]) == 0
    config = resolve_config(RunConfig, out / "config.toml")
    assert (config.network.kind, config.env.observation, config.env.size) == ("flat", "symbolic", "s")
    assert json.loads((out / "kinetix_import.json").read_text())["source"].endswith("params.safetensors")
    trainer, _, _, levels = build(config)  # the template `impulse eval` restores with
    template = jax.eval_shape(trainer.init, jax.random.key(0), levels).train
    with Checkpointer(out / config.checkpoint.directory, config.checkpoint) as checkpoints:
        items, counters, _, _ = checkpoints.restore({TRAIN: template})
    expected = import_kinetix(read_kinetix_checkpoint(FIXTURES / "flat")).params
    restored = items[TRAIN].params
    np.testing.assert_array_equal(restored["params"]["torso"]["embed"]["kernel"],
                                  expected["params"]["torso"]["embed"]["kernel"])
    assert counters["update"] == 0
    assert main(["import-kinetix", str(FIXTURES / "flat"), "--out", str(out)]) == 1  # never overwrites a run

    # `impulse train --resume` fine-tunes the imported policy on fresh environments (the import holds no envs).
    run = FusedRun(config, out, (out / "config.toml").read_text(), resume=True, stop_after_updates=1)
    try:
        start = np.asarray(run.carry.train.params["params"]["torso"]["embed"]["kernel"])
        np.testing.assert_array_equal(start, expected["params"]["torso"]["embed"]["kernel"])
        run.start()
        run.cycle()
        assert run.update == 1 and run.finished()
        tuned = np.asarray(run.carry.train.params["params"]["torso"]["embed"]["kernel"])
        assert np.isfinite(tuned).all() and not np.array_equal(tuned, start)
    finally:
        run.close()
