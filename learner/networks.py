"""Policy and value networks (flax linen): a torso that embeds the observation, then separate actor and critic
MLP heads, as in Kinetix.

Torsos (`NetworkConfig.kind`):
- "transformer" (`EntityTransformer`, entity observation): one token per shape slot (polygons then circles) from
  per-type encoders, plus a learned summary token; layers of masked multi-head attention whose heads are shared
  out among the observation's 4 attention-mask channels (all shapes, same joint component, directly jointed,
  touching), each followed by a gated feed-forward step and message passing along joints (from-shape, to-shape,
  joint row -> message to the from-shape) and thrusters (shape, thruster row -> message to the shape). The
  embedding is the mean over the summary token and the active shapes.
- "entity" (`PermutationInvariantMLP`, entity observation): every entity row (polygon, circle, joint direction,
  thruster) is encoded by its type's Dense layer and tagged with a type one-hot, passed through a multi-head
  Dense + ReLU, and summed over active entities: a set function, invariant to the order of slots.
- "flat" (`FlatMLP`, an array observation: the symbolic vector, the padded symbolic matrix or the blind one-hot,
  flattened): one Dense + ReLU layer.
- "cnn" (`PixelCNN`, pixel observation): Kinetix's two convolutions + ReLU, flattened, plus global_info.
Heads (`ActorCriticHeads`): `depth` x Dense(`width`) + activation for each of actor and critic (orthogonal init,
scale sqrt 2); actor output Dense(num_outputs) at scale 0.01, critic Dense(1) at scale 1. With a Gaussian policy
the actor adds a state-independent log-std parameter (initialised to 0), broadcast next to the means.

Settings that exist to run Kinetix's weights exactly (`learner.kinetix_import`): `summary_token="ones"` (its
constant dummy token), `sublayer_relu` (its ReLU before each gate), `shape_type_column` (its entity-id column)
and, for the permutation-invariant MLP, `count_inactive_entities` (its sum over all slots); all off by default.

Inactive entities (mask false) never influence the outputs: their rows are zeroed at the input, they are masked
out as attention keys, send no messages and are left out of sums and means (under `count_inactive_entities`
each adds a constant to the sum that does not depend on its features).

`ActorCritic(obs) -> (distribution params [..., P], value [...])` accepts observations with any leading
dimensions, none included: an `EntityObservation` whose leaves are [..., slots, features] (leading dimensions
read from `polygon_mask`), a `PixelObservation` (image [..., W, H, 3], global_info [..., 1]), or an array
[..., F] ([..., R, F] with `array_dims=2`). The distribution parameters are what the matching
`learner.distributions` object takes. Use `make_network(config, distribution)`, then `params =
network.init(key, obs)` and `network.apply(params, obs)` as the `apply_fn` of `learner.losses.ppo_loss`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.env.observation_types import ATTENTION_CHANNELS, EntityObservation, PixelObservation
from impulse.learner.config import NetworkConfig
from impulse.learner.distributions import DiagGaussian, Distribution

Array = jax.Array
NUM_ENTITY_TYPES = 4  # polygon, circle, joint, thruster
GATE_BIAS = 2.0  # initial pull of each gate towards passing its input through unchanged

_ACTIVATIONS: dict[str, Callable[[Array], Array]] = {"tanh": nn.tanh, "relu": nn.relu}


def _dense(features: int, scale: float = math.sqrt(2.0), name: str | None = None) -> nn.Dense:
    return nn.Dense(features, kernel_init=nn.initializers.orthogonal(scale), bias_init=nn.initializers.zeros, name=name)


def _masked(x: Array, mask: Array) -> Array:
    """Rows of x [..., n, d] where mask [..., n] is false set to 0 (a select, so nan or inf rows vanish too)."""
    return jnp.where(mask[..., None], x, 0.0)


class ActorCriticHeads(nn.Module):
    """Separate actor and critic MLPs over a shared embedding [B, E] -> (distribution params [B, P], value [B])."""

    config: NetworkConfig
    num_outputs: int
    gaussian: bool = False

    @nn.compact
    def __call__(self, embedding: Array) -> tuple[Array, Array]:
        act = _ACTIVATIONS[self.config.activation]
        actor, critic = embedding, embedding
        for i in range(self.config.depth):
            actor = act(_dense(self.config.width, name=f"actor_{i}")(actor))
            critic = act(_dense(self.config.width, name=f"critic_{i}")(critic))
        out = _dense(self.num_outputs, 0.01, name="actor_out")(actor)
        if self.gaussian:
            log_std = self.param("log_std", nn.initializers.zeros, (self.num_outputs,))
            out = jnp.concatenate([out, jnp.broadcast_to(log_std, out.shape)], axis=-1)
        value = _dense(1, 1.0, name="critic_out")(critic)[..., 0]
        return out, value


class GatedResidual(nn.Module):
    """GRU-style gate (Parisotto et al., 2019) in place of a residual sum: out = (1 - z) x + z h, with reset r and
    update z gates and candidate h = tanh(W y + U (r x)) from the stream x and the sublayer output y. z starts
    near 0.12, so a fresh layer mostly passes x through."""

    @nn.compact
    def __call__(self, x: Array, y: Array) -> Array:
        d = x.shape[-1]
        gates = nn.Dense(2 * d, name="gates_y")(y) + nn.Dense(2 * d, use_bias=False, name="gates_x")(x)
        reset = nn.sigmoid(gates[..., :d])
        update = nn.sigmoid(gates[..., d:] - GATE_BIAS)
        candidate = nn.tanh(
            nn.Dense(d, name="candidate_y")(y) + nn.Dense(d, use_bias=False, name="candidate_x")(reset * x)
        )
        return (1.0 - update) * x + update * candidate


class MaskedAttention(nn.Module):
    """Multi-head self-attention over tokens [B, L, D] with a per-head boolean mask [B, H, L, L] (query, key).
    Every query must have at least one allowed key."""

    num_heads: int
    head_size: int

    @nn.compact
    def __call__(self, x: Array, mask: Array) -> Array:
        shape = (self.num_heads, self.head_size)
        q = nn.DenseGeneral(shape, name="query")(x)
        k = nn.DenseGeneral(shape, name="key")(x)
        v = nn.DenseGeneral(shape, name="value")(x)
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, k) / math.sqrt(self.head_size)
        weights = jax.nn.softmax(jnp.where(mask, logits, -1e30), axis=-1)
        out = jnp.einsum("bhqk,bkhd->bqhd", weights, v)
        return nn.DenseGeneral(x.shape[-1], axis=(-2, -1), name="out")(out)


def _gather_rows(tokens: Array, index: Array) -> Array:
    """tokens [B, N, D] at index [B, M] -> [B, M, D]."""
    return jnp.take_along_axis(tokens, index[..., None], axis=1)


def _scatter_add(messages: Array, index: Array, num_rows: int) -> Array:
    """Sum messages [B, M, D] into rows index [B, M] of a [B, num_rows, D] array (one-hot matmul: M, N small)."""
    return jnp.einsum("bmn,bmd->bnd", jax.nn.one_hot(index, num_rows, dtype=messages.dtype), messages)


class TransformerLayer(nn.Module):
    """Pre-norm masked attention and feed-forward, each through a gate, then joint and thruster messages."""

    config: NetworkConfig

    @nn.compact
    def __call__(
        self,
        tokens: Array,  # [B, 1 + N, D], summary token first
        attention_mask: Array,  # [B, H, 1 + N, 1 + N]
        joints: Array,  # [B, 2J, D] encoded, zero where inactive
        joint_mask: Array,
        joint_indexes: Array,  # [B, 2J, 2] (from, to) shape indices
        thrusters: Array,  # [B, T, D]
        thruster_mask: Array,
        thruster_indexes: Array,  # [B, T]
    ) -> Array:
        cfg = self.config
        d = tokens.shape[-1]
        act = nn.relu if cfg.sublayer_relu else _ACTIVATIONS[cfg.activation]
        attended = MaskedAttention(cfg.num_heads, cfg.transformer_size)(nn.LayerNorm()(tokens), attention_mask)
        if cfg.sublayer_relu:
            attended = nn.relu(attended)
        tokens = GatedResidual(name="attention_gate")(tokens, attended)
        fed = act(nn.Dense(d, name="feed_forward")(nn.LayerNorm()(tokens)))
        tokens = GatedResidual(name="feed_forward_gate")(tokens, fed)

        summary, shapes = tokens[:, :1], tokens[:, 1:]
        n = shapes.shape[1]
        source, target = joint_indexes[..., 0], joint_indexes[..., 1]
        joint_in = jnp.concatenate([_gather_rows(shapes, source), _gather_rows(shapes, target), joints], axis=-1)
        joint_messages = _masked(nn.Dense(d, name="joint_message")(joint_in), joint_mask)
        thruster_in = jnp.concatenate([_gather_rows(shapes, thruster_indexes), thrusters], axis=-1)
        thruster_messages = _masked(nn.Dense(d, name="thruster_message")(thruster_in), thruster_mask)
        shapes = shapes + _scatter_add(joint_messages, source, n) + _scatter_add(thruster_messages, thruster_indexes, n)
        return jnp.concatenate([summary, shapes], axis=1)


def _head_masks(attention_mask: Array, shape_mask: Array, num_heads: int, full: bool) -> Array:
    """Per-head masks [B, H, 1 + N, 1 + N] over (summary token, shapes): the observation's channels restricted to
    active shapes, each channel given to num_heads / 4 consecutive heads (or channel 0 to all when `full`);
    the summary token may attend to every active shape and every token may attend to the summary token."""
    b, n = shape_mask.shape
    active = shape_mask[:, None, :, None] & shape_mask[:, None, None, :]
    channels = attention_mask.astype(bool) & active  # [B, 4, N, N]
    top = jnp.broadcast_to(shape_mask[:, None, None, :], (b, ATTENTION_CHANNELS, 1, n))
    channels = jnp.concatenate([top, channels], axis=2)
    channels = jnp.concatenate([jnp.ones((b, ATTENTION_CHANNELS, n + 1, 1), bool), channels], axis=3)
    channel_of_head = np.zeros(num_heads, int) if full else np.arange(num_heads) // (num_heads // ATTENTION_CHANNELS)
    return channels[:, channel_of_head]


class EntityTransformer(nn.Module):
    """Entity observation [B, ...] -> embedding [B, transformer_encoder_size]."""

    config: NetworkConfig

    @nn.compact
    def __call__(self, obs: EntityObservation) -> Array:
        cfg = self.config
        d = cfg.transformer_encoder_size
        act = _ACTIVATIONS[cfg.activation]

        def encode(rows: Array, mask: Array, name: str, type_value: float | None = None) -> Array:
            if type_value is None:
                return _masked(act(_dense(d, name=name)(_masked(rows, mask))), mask)
            encoded = act(_dense(d - 1, name=name)(_masked(rows, mask)))
            column = jnp.full(encoded.shape[:-1] + (1,), type_value, encoded.dtype)
            return _masked(jnp.concatenate([encoded, column], axis=-1), mask)

        polygon_type, circle_type = {"none": (None, None), "type": (1.0, 0.0), "zero": (0.0, 0.0)}[
            cfg.shape_type_column]
        shape_mask = jnp.concatenate([obs.polygon_mask, obs.circle_mask], axis=1).astype(bool)
        joint_mask, thruster_mask = obs.joint_mask.astype(bool), obs.thruster_mask.astype(bool)
        shapes = jnp.concatenate(
            [
                encode(obs.polygons, obs.polygon_mask, "polygon_encoder", polygon_type),
                encode(obs.circles, obs.circle_mask, "circle_encoder", circle_type),
            ],
            axis=1,
        )
        joints = encode(obs.joints, joint_mask, "joint_encoder")
        thrusters = encode(obs.thrusters, thruster_mask, "thruster_encoder")
        if cfg.summary_token == "ones":
            summary = jnp.ones((d,), shapes.dtype)
        else:
            summary = self.param("summary_token", nn.initializers.ones, (d,))
        tokens = jnp.concatenate([jnp.broadcast_to(summary, (shapes.shape[0], 1, d)), shapes], axis=1)
        mask = _head_masks(obs.attention_mask, shape_mask, cfg.num_heads, cfg.full_attention_mask)
        joint_indexes = obs.joint_indexes.astype(jnp.int32)
        thruster_indexes = obs.thruster_indexes.astype(jnp.int32)
        for i in range(cfg.transformer_layers):
            tokens = TransformerLayer(cfg, name=f"layer_{i}")(
                tokens, mask, joints, joint_mask, joint_indexes, thrusters, thruster_mask, thruster_indexes
            )
        token_mask = jnp.concatenate([jnp.ones_like(shape_mask[:, :1]), shape_mask], axis=1)
        return _masked(tokens, token_mask).sum(axis=1) / token_mask.sum(axis=1, keepdims=True)


class PermutationInvariantMLP(nn.Module):
    """Entity observation [B, ...] -> embedding [B, entity_heads * entity_head_size]: a sum over entities."""

    config: NetworkConfig

    @nn.compact
    def __call__(self, obs: EntityObservation) -> Array:
        cfg = self.config
        act = _ACTIVATIONS[cfg.activation]
        width = cfg.entity_encoder_size - NUM_ENTITY_TYPES
        groups = [
            (obs.polygons, obs.polygon_mask, "polygon_encoder"),
            (obs.circles, obs.circle_mask, "circle_encoder"),
            (obs.joints, obs.joint_mask, "joint_encoder"),
            (obs.thrusters, obs.thruster_mask, "thruster_encoder"),
        ]
        entities, masks = [], []
        for type_id, (rows, mask, name) in enumerate(groups):
            mask = mask.astype(bool)
            encoded = act(_dense(width, name=name)(_masked(rows, mask)))
            one_hot = jnp.broadcast_to(
                jax.nn.one_hot(type_id, NUM_ENTITY_TYPES), encoded.shape[:-1] + (NUM_ENTITY_TYPES,)
            )
            entities.append(jnp.concatenate([encoded, one_hot], axis=-1))
            masks.append(mask)
        entities, mask = jnp.concatenate(entities, axis=1), jnp.concatenate(masks, axis=1)
        if cfg.count_inactive_entities:
            heads = nn.relu(_dense(cfg.entity_heads * cfg.entity_head_size, name="multi_head")(_masked(entities, mask)))
            return act(heads.sum(axis=1))
        heads = nn.relu(_dense(cfg.entity_heads * cfg.entity_head_size, name="multi_head")(entities))
        return act(_masked(heads, mask).sum(axis=1))


class FlatMLP(nn.Module):
    """Array observation [B, ...] (a symbolic vector, the padded symbolic matrix or the blind one-hot), flattened
    per environment -> embedding [B, flat_embedding_size]."""

    config: NetworkConfig

    @nn.compact
    def __call__(self, obs: Array) -> Array:
        return nn.relu(_dense(self.config.flat_embedding_size, name="embed")(obs.reshape(obs.shape[0], -1)))


class PixelCNN(nn.Module):
    """Pixel observation (image [B, W, H, 3]) -> embedding [B, (W / 8) (H / 8) 32 + 1]: Kinetix's pixel torso,
    Conv 16 (8x8, stride 4) + ReLU, Conv 32 (4x4, stride 2) + ReLU (flax defaults: SAME padding, LeCun init),
    flattened, with global_info appended (gravity cannot be seen in the image)."""

    config: NetworkConfig

    @nn.compact
    def __call__(self, obs: PixelObservation) -> Array:
        x = nn.relu(nn.Conv(16, kernel_size=(8, 8), strides=(4, 4), name="conv_0")(obs.image))
        x = nn.relu(nn.Conv(32, kernel_size=(4, 4), strides=(2, 2), name="conv_1")(x))
        return jnp.concatenate([x.reshape(x.shape[0], -1), obs.global_info], axis=-1)


_TORSOS: dict[str, type[nn.Module]] = {
    "transformer": EntityTransformer,
    "entity": PermutationInvariantMLP,
    "flat": FlatMLP,
    "cnn": PixelCNN,
}


def _batch_shape(obs: EntityObservation | PixelObservation | Array, array_dims: int) -> tuple[int, ...]:
    if isinstance(obs, EntityObservation):
        return obs.polygon_mask.shape[:-1]
    if isinstance(obs, PixelObservation):
        return obs.global_info.shape[:-1]
    return obs.shape[: obs.ndim - array_dims]


class ActorCritic(nn.Module):
    """Torso by `config.kind`, then actor and critic heads: obs [..., ...] -> (params [..., P], value [...]).
    P = num_outputs, or 2 * num_outputs (means, then log-stds) when `gaussian`. `array_dims`: the dimensions of
    one environment's array observation (1 for a vector, 2 for the padded symbolic matrix)."""

    config: NetworkConfig
    num_outputs: int
    gaussian: bool = False
    array_dims: int = 1

    @nn.compact
    def __call__(self, obs: EntityObservation | PixelObservation | Array) -> tuple[Array, Array]:
        given = type(obs).__name__ if isinstance(obs, EntityObservation | PixelObservation) else "array"
        if self.config.kind == "flat" and given != "array":
            raise TypeError(f'network kind "flat" takes an array observation (symbolic, symbolic_padded or blind), '
                            f"got {given}")
        if self.config.kind == "cnn" and given != "PixelObservation":
            raise TypeError(f'network kind "cnn" takes a PixelObservation, got {given}')
        if self.config.kind not in ("flat", "cnn") and given != "EntityObservation":
            raise TypeError(f'network kind "{self.config.kind}" takes an EntityObservation, got {given}')
        batch = _batch_shape(obs, self.array_dims)
        size = int(np.prod(batch, dtype=int))
        leading = len(batch)
        flat_obs = jax.tree.map(lambda x: x.reshape((size,) + x.shape[leading:]), obs)
        embedding = _TORSOS[self.config.kind](self.config, name="torso")(flat_obs)
        dist_params, value = ActorCriticHeads(self.config, self.num_outputs, self.gaussian, name="heads")(embedding)
        return dist_params.reshape(batch + dist_params.shape[1:]), value.reshape(batch)


def make_network(config: NetworkConfig, distribution: Distribution, array_dims: int = 1) -> ActorCritic:
    """The actor-critic whose outputs parameterise `distribution` (see `learner.distributions.distribution_for`);
    `array_dims` as in `ActorCritic`."""
    if isinstance(distribution, DiagGaussian):
        return ActorCritic(config, distribution.dim, gaussian=True, array_dims=array_dims)
    return ActorCritic(config, distribution.num_params, array_dims=array_dims)


def count_parameters(params: Any) -> int:
    """Number of scalars in a parameter tree."""
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(params))


def parameter_counts(params: Any, depth: int = 2) -> dict[str, int]:
    """Parameter counts per module path, `depth` levels below the top (e.g. "torso/layer_0", "heads/actor_0"),
    plus "total"."""
    counts: dict[str, int] = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        keys = [str(getattr(k, "key", k)) for k in path if str(getattr(k, "key", k)) != "params"]
        name = "/".join(keys[:depth])
        counts[name] = counts.get(name, 0) + int(np.prod(leaf.shape))
    counts["total"] = count_parameters(params)
    return counts


def describe_parameters(params: Any, depth: int = 2) -> str:
    """A printable table of `parameter_counts`."""
    counts = parameter_counts(params, depth)
    width = max(len(k) for k in counts)
    return "\n".join(f"{name:<{width}}  {count:>10,}" for name, count in counts.items())
