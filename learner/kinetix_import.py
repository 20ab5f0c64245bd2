"""Policies trained with Kinetix 3.0.x, read from its checkpoint files and mapped onto our networks exactly.

Why: a Kinetix user should be able to bring a trained policy (their own, or the published general agents) and
get the same action distribution and value for the same observation. Nothing is approximated: every Kinetix
setting that changes the outputs either has a faithful counterpart in `NetworkConfig` (set by the import) or
the import is refused with a `KinetixImportError` naming it.

Files read (`read_kinetix_checkpoint`):
- the training scripts' `full_model.pbz2` (a bz2-compressed pickle of {"step", "params", "opt_state", "extra"})
  or `params.pbz2` / `model.pbz2` (the parameters alone). Pickles are read with a restricted unpickler: arrays,
  plain containers and flax's FrozenDict are rebuilt, any other class (optimiser states, the "extra" payload) is
  kept as an inert placeholder and never imported or run. Such checkpoints carry no model settings; those that
  cannot be read off the parameter shapes take Kinetix's defaults unless given as options.
- the pretrained format: a directory with `params.safetensors` (the flax tree flattened with "/") and
  `config.json` whose "model" entry holds the settings the network was built with: what Kinetix's
  `load_pretrained_checkpoint` reads, the loader it offers for downloaded checkpoints such as the general agents.

Mapping (`import_kinetix`): the three architectures Kinetix builds for symbolic observations, and its pixel CNN.
- Entity transformer -> kind "transformer" with `summary_token="ones"` (Kinetix's constant dummy token),
  `sublayer_relu` (its ReLU before each gate), `shape_type_column` "type" or, for `legacy_entity_id`, "zero";
  flax's multi-head attention splits `transformer_size` features over the heads, ours counts them per head. Its
  gate's six bias-free Dense layers and learned gate bias become our four gate layers and their biases.
- Permutation-invariant MLP -> kind "entity" with `count_inactive_entities`; the per-head kernels become one
  Dense layer, and the circle/polygon type one-hot columns are swapped (Kinetix numbers circles first).
- Flat MLP -> kind "flat".
- Pixel network, `cnn_mode` "impala_fast" (two convolutions) -> kind "cnn"; the pixel downscale it was trained at
  is read off the heads' input size.
Refused: recurrent heads (GRU), actor and critic of different shapes, separate actor/critic embeddings, the
transformer's FFN and multi-layer message blocks, aggregate modes other than "dummy_and_mean", the resnet_18
pixel network, padded-flat and blind observations, hybrid actions, and checkpoints that carry
observation-normalisation statistics.
"""

from __future__ import annotations

import bz2
import dataclasses
import io
import json
import math
import pickle
import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import numpy as np

from impulse.engine.env.actions import action_space
from impulse.engine.env.config import EnvConfig
from impulse.engine.env.observations import symbolic_length
from impulse.engine.env.pixels import SCREEN_PIXELS
from impulse.engine.env.spec import env_from_config
from impulse.learner.config import NetworkConfig
from impulse.learner.distributions import DiagGaussian, distribution_for
from impulse.learner.networks import GATE_BIAS, NUM_ENTITY_TYPES, make_network

PRETRAINED_PARAMS = "params.safetensors"
PRETRAINED_CONFIG = "config.json"
PICKLE_NAMES = ("full_model.pbz2", "params.pbz2", "model.pbz2")

KINETIX_DEFAULTS: dict[str, Any] = {
    "activation": "tanh",
    "full_attention_mask": False,
    "aggregate_mode": "dummy_and_mean",
    "legacy_entity_id": False,
    "recurrent_model": False,
    "transformer_ffn": False,
    "multilayer_joint_thruster_mixing": False,
    "separate_actor_critic": False,
}
"""Kinetix 3.0.2's model defaults (configs/model/*.yaml) for the settings the parameters do not reveal."""

SIZE_OF_FLAT_LENGTH = {symbolic_length(env_from_config(EnvConfig(size=s))[0].sizes): s for s in ("s", "m", "l")}

Flat = dict[tuple[str, ...], np.ndarray]


class KinetixImportError(ValueError):
    """A Kinetix checkpoint that cannot be read, or whose network our networks cannot reproduce exactly."""


@dataclass
class KinetixCheckpoint:
    """What a Kinetix checkpoint holds: its parameters (flattened, without the leading "params") and whatever
    model settings it records."""

    params: Flat
    options: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    unread_classes: set[str] = field(default_factory=set)
    """Classes found in the pickle and left as placeholders (e.g. optimiser states)."""


@dataclass
class ImportedPolicy:
    """Our network settings, our parameter tree ({"params": ...}, numpy) and the environment settings it needs."""

    network: NetworkConfig
    params: dict[str, Any]
    observation: str
    action: str
    size: str | None
    """Set when the parameters fix the size (flat observation lengths differ per size)."""
    settings: dict[str, Any]
    """The Kinetix model settings the mapping used, and for each whether it came from the checkpoint."""
    pixel_downscale: int | None = None
    """Set for pixel networks: the image size their heads were trained on fixes it."""


# ---------------------------------------------------------------------------------------------------- reading


class _Opaque:
    """Stand-in for a class the restricted unpickler will not import: swallows its arguments and state."""

    qualified_name = "?"

    def __new__(cls, *args: Any, **kwargs: Any) -> _Opaque:
        return object.__new__(cls)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def __repr__(self) -> str:
        return f"<unread {self.qualified_name}>"


def _array_from_jax_pickle(fun: Any, args: Any, arr_state: Any, aval_state: Any) -> np.ndarray:
    """A pickled jax.Array rebuilt as the numpy array it wraps (no device, no jax import needed)."""
    del aval_state
    value = fun(*args)
    value.__setstate__(arr_state)
    return value


def _new_ndarray(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
    """numpy's pickle constructor, always of a plain ndarray (its state is set next)."""
    del subtype
    return np.ndarray.__new__(np.ndarray, shape, dtype)


class _RestrictedUnpickler(pickle.Unpickler):
    """Rebuilds arrays and containers only; every other class becomes an inert `_Opaque` subclass."""

    ALLOWED: Mapping[tuple[str, str], Any] = {
        ("builtins", "dict"): dict, ("builtins", "list"): list, ("builtins", "tuple"): tuple,
        ("builtins", "set"): set, ("builtins", "frozenset"): frozenset, ("builtins", "int"): int,
        ("builtins", "float"): float, ("builtins", "complex"): complex, ("builtins", "str"): str,
        ("builtins", "bytes"): bytes, ("builtins", "bool"): bool, ("builtins", "slice"): slice,
        ("collections", "OrderedDict"): dict,
        ("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype,
        ("numpy.core.multiarray", "_reconstruct"): _new_ndarray,
        ("numpy._core.multiarray", "_reconstruct"): _new_ndarray,
        ("jax._src.array", "_reconstruct_array"): _array_from_jax_pickle,
        ("flax.core.frozen_dict", "FrozenDict"): dict,
    }

    def __init__(self, file: io.BufferedIOBase):
        super().__init__(file)
        self.unread: set[str] = set()

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self.ALLOWED:
            return self.ALLOWED[(module, name)]
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "scalar":
            return _numpy_scalar
        qualified = f"{module}.{name}"
        self.unread.add(qualified)
        return type(name, (_Opaque,), {"qualified_name": qualified})


def _numpy_scalar(dtype: np.dtype, data: bytes | None = None) -> Any:
    return np.frombuffer(data or b"", dtype=dtype)[0]


def read_pickle(path: Path) -> tuple[Any, set[str]]:
    """A Kinetix `.pbz2` file's object, and the classes left unread."""
    with bz2.open(path, "rb") as f:
        unpickler = _RestrictedUnpickler(f)  # type: ignore[arg-type]
        try:
            obj = unpickler.load()
        except (pickle.UnpicklingError, EOFError, OSError, TypeError, ValueError) as err:
            raise KinetixImportError(f"{path} is not a Kinetix .pbz2 checkpoint: {err}") from err
    return obj, unpickler.unread


_SAFETENSORS_DTYPES = {"F64": "<f8", "F32": "<f4", "F16": "<f2", "I64": "<i8", "I32": "<i4", "I16": "<i2",
                       "I8": "i1", "U8": "u1", "BOOL": "?"}


def read_safetensors(path: Path) -> dict[str, np.ndarray]:
    """A safetensors file as {name: array}, read with numpy (the format is a JSON header and raw bytes)."""
    data = Path(path).read_bytes()
    if len(data) < 8:
        raise KinetixImportError(f"{path} is not a safetensors file (too short)")
    (header_len,) = struct.unpack("<Q", data[:8])
    try:
        header = json.loads(data[8:8 + header_len])
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise KinetixImportError(f"{path} is not a safetensors file: {err}") from err
    body = memoryview(data)[8 + header_len:]
    arrays = {}
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        begin, end = entry["data_offsets"]
        if entry["dtype"] == "BF16":
            import ml_dtypes

            dtype: Any = ml_dtypes.bfloat16
        elif entry["dtype"] in _SAFETENSORS_DTYPES:
            dtype = np.dtype(_SAFETENSORS_DTYPES[entry["dtype"]])
        else:
            raise KinetixImportError(f"{path}: tensor {name} has unsupported dtype {entry['dtype']}")
        arrays[name] = np.frombuffer(body[begin:end], dtype=dtype).reshape(entry["shape"]).copy()
    return arrays


def _flatten(tree: Any, prefix: tuple[str, ...] = ()) -> Flat:
    if isinstance(tree, Mapping):
        out: Flat = {}
        for key, value in tree.items():
            out.update(_flatten(value, prefix + (str(key),)))
        return out
    if isinstance(tree, _Opaque):
        raise KinetixImportError(f"parameter {'/'.join(prefix)} is an object of class {tree.qualified_name}, "
                                 "not an array")
    return {prefix: np.asarray(tree)}


def _params_of(obj: Any, path: Path) -> Any:
    """The {"Dense_0": ...} module tree inside a pickled checkpoint, whichever of Kinetix's layouts it has."""
    node = obj
    for _ in range(3):
        if isinstance(node, Mapping) and "params" in node:
            node = node["params"]
        else:
            break
    if not isinstance(node, Mapping) or not node:
        raise KinetixImportError(f"{path}: no parameter tree found (expected a dict with 'params')")
    return node


def read_kinetix_checkpoint(path: str | Path, config_json: str | Path | None = None) -> KinetixCheckpoint:
    """Read a Kinetix checkpoint: a pretrained directory (params.safetensors + config.json), a directory holding
    full_model.pbz2 or model.pbz2, or such a file itself. `config_json` names a Kinetix config file with the model
    settings (`read_kinetix_config`), for checkpoints that do not carry them."""
    path = Path(path)
    options: dict[str, Any] = {}
    unread: set[str] = set()
    if path.is_dir():
        if (path / PRETRAINED_PARAMS).is_file():
            config_json = config_json or (path / PRETRAINED_CONFIG if (path / PRETRAINED_CONFIG).is_file() else None)
            path = path / PRETRAINED_PARAMS
        else:
            found = [path / name for name in PICKLE_NAMES if (path / name).is_file()]
            if not found:
                raise KinetixImportError(f"{path} holds none of {PRETRAINED_PARAMS}, {', '.join(PICKLE_NAMES)}")
            path = found[0]
    if not path.is_file():
        raise KinetixImportError(f"no such checkpoint file: {path}")
    if path.suffix == ".safetensors":
        flat = {tuple(k.split("/")): v for k, v in read_safetensors(path).items()}
    else:
        obj, unread = read_pickle(path)
        flat = _flatten(_params_of(obj, path))
    flat = {k[1:] if k and k[0] == "params" else k: v for k, v in flat.items()}
    if config_json is not None:
        options = read_kinetix_config(config_json)
    return KinetixCheckpoint(flat, options, str(path), unread)


def model_options(config: Mapping[str, Any]) -> dict[str, Any]:
    """Model settings from a Kinetix config: its "model" entry merged over the top level (Kinetix's flattened
    configs keep them at the top), "observation_type"/"action_type" and the size included when present; the
    older fc_layer_depth/fc_layer_width names stand for both heads' depth and width."""
    merged = {k: v for k, v in config.items() if not isinstance(v, Mapping)}
    for section in ("env", "env_size", "model"):
        if isinstance(config.get(section), Mapping):
            merged.update(config[section])
    for key in ("observation_type", "action_type"):
        if f"{key}_str" in merged:
            merged[key] = merged[f"{key}_str"]
    for old, new in (("fc_layer_depth", ("actor_depth", "critic_depth")), ("fc_layer_width", ("actor_width",
                                                                                          "critic_width"))):
        if old in merged:
            for key in new:
                merged.setdefault(key, merged[old])
    return merged


def read_kinetix_config(path: str | Path) -> dict[str, Any]:
    """Model settings from a Kinetix config file: a pretrained checkpoint's config.json, or the config.yaml a
    Kinetix training run writes under logs/."""
    path = Path(path)
    text = path.read_text()
    if path.suffix in (".yaml", ".yml"):
        import yaml

        loaded = yaml.safe_load(text)
    else:
        loaded = json.loads(text)
    if not isinstance(loaded, Mapping):
        raise KinetixImportError(f"{path} does not hold a Kinetix config (a mapping of settings)")
    return model_options(loaded)


# ---------------------------------------------------------------------------------------------------- mapping


class _Settings:
    """Kinetix model settings: the checkpoint's, else given options, else Kinetix's defaults; records which."""

    def __init__(self, recorded: Mapping[str, Any], given: Mapping[str, Any]):
        self.values = {**recorded, **given}
        self.used: dict[str, Any] = {}

    def get(self, key: str, default: Any = None) -> Any:
        if key in self.values:
            value, source = self.values[key], "checkpoint/options"
        elif key in KINETIX_DEFAULTS:
            value, source = KINETIX_DEFAULTS[key], "Kinetix default"
        else:
            value, source = default, "parameters"
        self.used[key] = {"value": value, "from": source}
        return value


def _agree(settings: _Settings, found: Mapping[str, int]) -> None:
    """Sizes read off the parameters must match the ones the settings state, if they state any: a config file
    from another run is an error, not a silent mismatch."""
    for key, value in found.items():
        if key in settings.values and settings.values[key] != value:
            raise KinetixImportError(f"the settings say {key}={settings.values[key]!r} but the parameters have "
                                     f"{value}: is the config from another run?")


def _module(params: Flat, *prefix: str) -> Flat:
    n = len(prefix)
    return {k[n:]: v for k, v in params.items() if k[:n] == prefix}


def _dense(params: Flat, *prefix: str, bias: bool = True) -> dict[str, np.ndarray]:
    layer = _module(params, *prefix)
    if ("kernel",) not in layer:
        raise KinetixImportError(f"the checkpoint has no Dense layer {'/'.join(prefix)}")
    out = {"kernel": layer[("kernel",)]}
    if bias:
        out["bias"] = layer[("bias",)] if ("bias",) in layer else np.zeros(out["kernel"].shape[-1], np.float32)
    return out


def _numbered(params: Flat, stem: str, *prefix: str) -> int:
    """How many of `prefix/stem_0`, `prefix/stem_1`, ... exist."""
    n = len(prefix)
    names = {k[n] for k in params if k[:n] == prefix and len(k) > n}
    count = 0
    while f"{stem}_{count}" in names:
        count += 1
    return count


def _heads(params: Flat, settings: _Settings) -> tuple[dict[str, Any], int, int, bool, int]:
    """Our heads' parameters from GeneralActorCriticRNN_0: (tree, width, depth, gaussian, outputs)."""
    root = ("GeneralActorCriticRNN_0",)
    if any(k[:1] == ("ScannedRNN_0",) or "ScannedRNN_0" in k for k in params) or settings.get("recurrent_model"):
        raise KinetixImportError("the checkpoint's network is recurrent (a GRU before the heads, "
                                 "recurrent_model=true); Impulse's networks are feed-forward")
    layers = _numbered(params, "DenseAndActivation", *root)
    actor_depth, critic_depth = settings.get("actor_depth", layers // 2), settings.get("critic_depth", layers // 2)
    if actor_depth != critic_depth or actor_depth + critic_depth != layers:
        raise KinetixImportError(f"actor depth {actor_depth} and critic depth {critic_depth} ({layers} layers in "
                                 "all) differ; Impulse's heads have one depth for both")
    if _numbered(params, "Dense", *root) != 2:
        raise KinetixImportError("the heads have extra output layers (hybrid actions?); only discrete, "
                                 "multi-discrete and continuous actions are supported")
    tree: dict[str, Any] = {}
    widths = set()
    for i in range(layers):
        dense = _dense(params, *root, f"DenseAndActivation_{i}", "Dense_0")
        widths.add(dense["kernel"].shape[1])
        tree[f"actor_{i}" if i < actor_depth else f"critic_{i - actor_depth}"] = dense
    if len(widths) > 1:
        raise KinetixImportError(f"the head layers have different widths {sorted(widths)}; Impulse's heads have one")
    tree["actor_out"] = _dense(params, *root, "Dense_0")
    tree["critic_out"] = _dense(params, *root, "Dense_1")
    gaussian = root + ("log_std",) in params
    if gaussian:
        tree["log_std"] = params[root + ("log_std",)]
    width = widths.pop() if widths else tree["actor_out"]["kernel"].shape[0]
    _agree(settings, {"actor_width": width, "critic_width": width})
    return tree, width, actor_depth, gaussian, tree["actor_out"]["kernel"].shape[1]


def _gate(gate: Flat) -> dict[str, Any]:
    """Kinetix's gate (reset: Dense_0 y + Dense_1 x; update: Dense_2 y + Dense_3 x - gating_bias; candidate:
    Dense_4 y + Dense_5 (r x)) as our GatedResidual, whose update gate subtracts the constant GATE_BIAS."""
    k = {i: gate[(f"Dense_{i}", "kernel")] for i in range(6)}
    if ("Dense_0", "bias") in gate:
        raise KinetixImportError("unexpected biases in a transformer gate")
    d = k[0].shape[0]
    gating_bias = gate[("gating_bias",)]
    return {
        "gates_y": {"kernel": np.concatenate([k[0], k[2]], axis=1),
                    "bias": np.concatenate([np.zeros(d, np.float32), GATE_BIAS - gating_bias]).astype(np.float32)},
        "gates_x": {"kernel": np.concatenate([k[1], k[3]], axis=1)},
        "candidate_y": {"kernel": k[4], "bias": np.zeros(d, np.float32)},
        "candidate_x": {"kernel": k[5]},
    }


def _transformer(params: Flat, settings: _Settings) -> tuple[dict[str, Any], dict[str, Any]]:
    if settings.get("transformer_ffn") or ("Transformer_0", "tf_layers_0", "dense2", "kernel") in params:
        raise KinetixImportError("transformer_ffn=true (a 4x-wide feed-forward block) is not represented in "
                                 "Impulse's transformer")
    if settings.get("multilayer_joint_thruster_mixing") or any(
            k[:2] == ("Transformer_0", "joint_layers_0") and len(k) > 3 for k in params):
        raise KinetixImportError("multilayer_joint_thruster_mixing=true (multi-layer message blocks) is not "
                                 "represented in Impulse's transformer")
    aggregate = settings.get("aggregate_mode")
    if aggregate != "dummy_and_mean":
        raise KinetixImportError(f"aggregate_mode={aggregate!r}: Impulse's transformer embeds a scene as the mean "
                                 "over the dummy token and the active shapes (Kinetix's 'dummy_and_mean') only")
    root = ("Transformer_0",)
    depth = _numbered(params, "tf_layers", *root)
    torso: dict[str, Any] = {
        "circle_encoder": _dense(params, "Dense_0"),
        "polygon_encoder": _dense(params, "Dense_1"),
        "joint_encoder": _dense(params, "Dense_2"),
        "thruster_encoder": _dense(params, "Dense_3"),
    }
    d = torso["joint_encoder"]["kernel"].shape[1]
    if torso["polygon_encoder"]["kernel"].shape[1] != d - 1:
        raise KinetixImportError("the shape encoders are not one unit narrower than the token width (no entity "
                                 "id column): not Kinetix 3.0's entity transformer")
    query = params[root + ("tf_layers_0", "attention1", "query", "kernel")]
    heads, head_size = query.shape[1], query.shape[2]
    for i in range(depth):
        layer = _module(params, *root, f"tf_layers_{i}")
        attention = _module(layer, "attention1")
        torso[f"layer_{i}"] = {
            "LayerNorm_0": {"scale": layer[("ln1", "scale")], "bias": layer[("ln1", "bias")]},
            "LayerNorm_1": {"scale": layer[("ln2", "scale")], "bias": layer[("ln2", "bias")]},
            "MaskedAttention_0": {name: _dense(attention, name) for name in ("query", "key", "value", "out")},
            "attention_gate": _gate(_module(layer, "gate1")),
            "feed_forward": _dense(layer, "dense1"),
            "feed_forward_gate": _gate(_module(layer, "gate2")),
            "joint_message": _dense(params, *root, f"joint_layers_{i}"),
            "thruster_message": _dense(params, *root, f"thruster_layers_{i}"),
        }
    network = {
        "kind": "transformer", "transformer_layers": depth, "num_heads": heads, "transformer_size": head_size,
        "transformer_encoder_size": d, "full_attention_mask": bool(settings.get("full_attention_mask")),
        "summary_token": "ones", "sublayer_relu": True,
        "shape_type_column": "zero" if settings.get("legacy_entity_id") else "type",
    }
    _agree(settings, {"transformer_depth": depth, "num_heads": heads, "transformer_size": heads * head_size,
                      "transformer_encoder_size": d})
    if not network["full_attention_mask"] and heads % 4:
        raise KinetixImportError(f"{heads} attention heads cannot share out the 4 attention-mask channels")
    return torso, network


def _permutation_invariant(params: Flat, settings: _Settings) -> tuple[dict[str, Any], dict[str, Any]]:
    if ("MultiHeadDense_1", "dense_kernels") in params or settings.get("separate_actor_critic"):
        raise KinetixImportError("separate_actor_critic=true (separate multi-head embeddings for actor and "
                                 "critic) is not represented in Impulse's permutation-invariant MLP")
    kernels, biases = params[("MultiHeadDense_0", "dense_kernels")], params[("MultiHeadDense_0", "dense_biases")]
    heads, entity_size, head_size = kernels.shape
    width = entity_size - NUM_ENTITY_TYPES
    kernel = kernels.transpose(1, 0, 2).reshape(entity_size, heads * head_size).copy()
    # Kinetix's type one-hot numbers circles 0 and polygons 1; ours polygons 0 and circles 1.
    kernel[[width, width + 1]] = kernel[[width + 1, width]]
    torso = {
        "circle_encoder": _dense(params, "Dense_0"),
        "polygon_encoder": _dense(params, "Dense_1"),
        "joint_encoder": _dense(params, "Dense_2"),
        "thruster_encoder": _dense(params, "Dense_3"),
        "multi_head": {"kernel": kernel, "bias": biases.reshape(heads * head_size)},
    }
    if torso["polygon_encoder"]["kernel"].shape[1] != width:
        raise KinetixImportError("the entity encoders' width does not match the multi-head layer's input")
    _agree(settings, {"num_heads": heads, "encoder_size": entity_size, "symbolic_embedding_dim": heads * head_size})
    network = {"kind": "entity", "entity_encoder_size": entity_size, "entity_heads": heads,
               "entity_head_size": head_size, "count_inactive_entities": True}
    return torso, network


OBSERVATION_TYPES = ("pixels", "symbolic_flat", "symbolic_entity", "blind", "symbolic_flat_padded")
ACTION_TYPES = ("continuous", "discrete", "multi_discrete", "hybrid")
"""Kinetix's ObservationType and ActionType names in the order of their enum values."""


def _enum_name(value: Any, names: tuple[str, ...]) -> str:
    """A Kinetix enum setting as its name, whether saved as "symbolic_entity", "ObservationType.SYMBOLIC_ENTITY"
    or the enum's value."""
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < len(names):
        return names[value]
    return str(value).lower().rpartition(".")[2]


def _observation_type(settings: _Settings, params: Flat) -> str:
    if "Transformer_0" in {k[0] for k in params} or ("MultiHeadDense_0", "dense_kernels") in params:
        inferred = "symbolic_entity"
    elif any(k[0].startswith("Conv_") for k in params):
        inferred = "pixels"
    else:
        inferred = "symbolic_flat"
    given = _enum_name(settings.get("observation_type", inferred), OBSERVATION_TYPES)
    if given in ("symbolic_flat_padded", "blind"):
        raise KinetixImportError(f"observation_type={given}: only Kinetix's symbolic_entity, symbolic_flat and "
                                 "pixels networks can be imported")
    if given != inferred:
        raise KinetixImportError(f"the settings say observation_type={given} but the parameters are those of a "
                                 f"{inferred} network")
    return inferred


PIXEL_CONVOLUTIONS = (("Conv_0", "conv_0", (8, 8, 3, 16)), ("Conv_1", "conv_1", (4, 4, 16, 32)))
"""Kinetix's "impala_fast" pixel torso, layer by layer: (its name, ours, kernel shape)."""


def _pixel_cnn(params: Flat, settings: _Settings, embedding: int) -> tuple[dict[str, Any], int]:
    """Our "cnn" torso's parameters from Kinetix's impala_fast convolutions, and the pixel downscale the heads'
    input size (`embedding`: the flattened image features plus gravity) was trained at."""
    mode = settings.get("cnn_mode", "impala_fast")
    if mode != "impala_fast":
        raise KinetixImportError(f"cnn_mode={mode}: only Kinetix's impala_fast pixel network (two convolutions) "
                                 "has an Impulse counterpart")
    torso = {}
    for theirs, ours, shape in PIXEL_CONVOLUTIONS:
        layer = _dense(params, theirs)
        if tuple(layer["kernel"].shape) != shape:
            raise KinetixImportError(f"{theirs} has a {tuple(layer['kernel'].shape)} kernel, not impala_fast's "
                                     f"{shape} (another cnn_mode, such as resnet_18?)")
        torso[ours] = layer
    for downscale in range(1, SCREEN_PIXELS + 1):
        if SCREEN_PIXELS % downscale:
            continue
        side = math.ceil(math.ceil(SCREEN_PIXELS // downscale / 4) / 2)  # SAME padding, strides 4 then 2
        if side * side * PIXEL_CONVOLUTIONS[-1][2][-1] + 1 == embedding:
            return torso, downscale
    raise KinetixImportError(f"the heads read {embedding} features, which matches no pixel downscale of the "
                             f"{SCREEN_PIXELS} x {SCREEN_PIXELS} screen")


def _action_kind(settings: _Settings, gaussian: bool, outputs: int) -> str:
    counts = {kind: action_space(env_from_config(EnvConfig(action=kind))[0]).num_logits
              for kind in ("multi_discrete", "discrete")}
    if gaussian:
        inferred = "continuous"
    else:
        matches = [kind for kind, n in counts.items() if n == outputs]
        if len(matches) != 1:
            raise KinetixImportError(f"the actor has {outputs} outputs, which matches no Kinetix action type "
                                     f"(multi-discrete {counts['multi_discrete']}, discrete {counts['discrete']})")
        inferred = matches[0]
    given = _enum_name(settings.get("action_type", inferred), ACTION_TYPES)
    if given == "hybrid":
        raise KinetixImportError("hybrid actions have no Impulse counterpart")
    if given != inferred:
        raise KinetixImportError(f"the settings say action_type={given} but the actor's outputs are "
                                 f"those of {inferred} actions")
    return inferred


def import_kinetix(checkpoint: KinetixCheckpoint, options: Mapping[str, Any] | None = None) -> ImportedPolicy:
    """Our network settings and parameters reproducing a Kinetix checkpoint's network exactly, or a
    `KinetixImportError` naming what cannot be represented. `options` give Kinetix model settings the
    checkpoint does not record (e.g. {"activation": "relu"}); they override recorded ones."""
    settings = _Settings(checkpoint.options, options or {})
    normalisers = sorted(c for c in checkpoint.unread_classes if "RunningMeanStandard" in c)
    if normalisers and not settings.get("ignore_observation_normalisation", False):
        raise KinetixImportError(
            f"the checkpoint carries observation-normalisation statistics ({normalisers[0]}); Impulse's networks "
            "take raw observations, so a policy trained on normalised ones cannot be reproduced. If the run did "
            "not normalise observations, pass ignore_observation_normalisation=true")
    params = checkpoint.params
    if not params:
        raise KinetixImportError(f"{checkpoint.source}: empty parameter tree")
    activation = settings.get("activation")
    if activation not in ("tanh", "relu"):
        raise KinetixImportError(f"activation={activation!r}: Kinetix networks use tanh or relu")
    observation = _observation_type(settings, params)
    heads, width, depth, gaussian, outputs = _heads(params, settings)
    action = _action_kind(settings, gaussian, outputs)
    size, downscale = None, None
    if observation == "pixels":
        torso, downscale = _pixel_cnn(params, settings, heads["actor_0" if depth else "actor_out"]["kernel"].shape[0])
        network = {"kind": "cnn"}
    elif observation == "symbolic_flat":
        torso = {"embed": _dense(params, "Dense_0")}
        length, embedding = torso["embed"]["kernel"].shape
        if length not in SIZE_OF_FLAT_LENGTH:
            raise KinetixImportError(f"the flat network reads {length} features, which is no Kinetix size's flat "
                                     f"observation ({', '.join(f'{s}: {n}' for n, s in SIZE_OF_FLAT_LENGTH.items())})")
        size = SIZE_OF_FLAT_LENGTH[length]
        network = {"kind": "flat", "flat_embedding_size": embedding}
    elif ("MultiHeadDense_0", "dense_kernels") in params:
        torso, network = _permutation_invariant(params, settings)
    else:
        torso, network = _transformer(params, settings)
    known = {k for k in params if k[0] in ("Dense_0", "Dense_1", "Dense_2", "Dense_3", "Transformer_0",
                                           "MultiHeadDense_0", "GeneralActorCriticRNN_0", "Conv_0", "Conv_1")}
    if set(params) - known:
        extra = sorted("/".join(k) for k in set(params) - known)
        raise KinetixImportError(f"parameters the mapping does not know: {', '.join(extra[:5])}")
    config = NetworkConfig(width=width, depth=depth, activation=activation, **network)
    tree = {"params": {"torso": torso, "heads": heads}}
    tree = _as_float32(tree)
    ours = {"symbolic_entity": "entity", "symbolic_flat": "symbolic", "pixels": "pixels"}[observation]
    return ImportedPolicy(config, tree, ours, action, size, settings.used, downscale)


def _as_float32(tree: Any) -> Any:
    if isinstance(tree, dict):
        return {k: _as_float32(v) for k, v in tree.items()}
    return np.asarray(tree, np.float32)


def check_against(imported: ImportedPolicy, template: Any) -> None:
    """Raise if the imported tree differs from our network's own parameter tree (`template`, e.g. from
    `jax.eval_shape(network.init, ...)`) in any name or shape: the mapping and the network must agree exactly."""
    ours = {"/".join(str(getattr(p, "key", p)) for p in path): tuple(leaf.shape)
            for path, leaf in _leaves_with_path(template)}
    theirs = {"/".join(str(getattr(p, "key", p)) for p in path): tuple(leaf.shape)
              for path, leaf in _leaves_with_path(imported.params)}
    if ours != theirs:
        missing = sorted(set(ours) - set(theirs))
        unexpected = sorted(set(theirs) - set(ours))
        shapes = sorted(k for k in set(ours) & set(theirs) if ours[k] != theirs[k])
        raise KinetixImportError(
            "the imported parameters do not fit the network: "
            + "; ".join(f"{label}: {', '.join(f'{k} {ours.get(k)} vs {theirs.get(k)}' for k in keys[:4])}"
                        for label, keys in (("missing", missing), ("unexpected", unexpected), ("shape", shapes))
                        if keys))


def _leaves_with_path(tree: Any) -> list[tuple[tuple[Any, ...], Any]]:
    return jax.tree_util.tree_leaves_with_path(tree)


def describe_settings(imported: ImportedPolicy) -> str:
    """One line per Kinetix setting the import relied on, marking those taken from Kinetix's defaults."""
    lines = []
    for key, entry in sorted(imported.settings.items()):
        lines.append(f"  {key} = {entry['value']!r}  ({entry['from']})")
    return "\n".join(lines)


def env_overrides(imported: ImportedPolicy) -> dict[str, Any]:
    """The env settings an imported policy needs: observation, action and, for flat networks, size (for pixel
    networks, the pixel downscale)."""
    out: dict[str, Any] = {"observation": imported.observation, "action": imported.action}
    if imported.size is not None:
        out["size"] = imported.size
    if imported.pixel_downscale is not None:
        out["pixel_downscale"] = imported.pixel_downscale
    return out


def with_network(env: EnvConfig, imported: ImportedPolicy) -> EnvConfig:
    """`env` changed to what `imported` needs."""
    return dataclasses.replace(env, **env_overrides(imported))


def parse_option(text: str) -> tuple[str, Any]:
    """`key=value` as a Kinetix model setting: JSON values (true, 8, "relu"), else the plain string."""
    key, sep, raw = text.partition("=")
    if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
        raise KinetixImportError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(raw)
    except json.JSONDecodeError:
        return key, raw


def policy_outputs(imported: ImportedPolicy, obs: Any) -> tuple[np.ndarray, np.ndarray]:
    """(per-dimension log-probabilities, or Gaussian means then log-stds; values) of the imported network on a
    batch of observations: the numbers to compare with Kinetix's own, which is how an import is checked."""
    spec, _ = env_from_config(EnvConfig(**{"size": "s", **env_overrides(imported)}))
    distribution = distribution_for(action_space(spec))
    network = make_network(imported.network, distribution)
    check_against(imported, jax.eval_shape(network.init, jax.random.key(0), obs))
    params, value = jax.jit(network.apply)(imported.params, obs)
    if isinstance(distribution, DiagGaussian):
        return np.asarray(params), np.asarray(value)
    sizes = getattr(distribution, "nvec", None) or (distribution.n,)
    bounds = np.cumsum((0, *sizes))
    log_probs = [jax.nn.log_softmax(params[:, a:b], axis=-1) for a, b in zip(bounds[:-1], bounds[1:])]
    return np.concatenate(log_probs, axis=-1), np.asarray(value)
