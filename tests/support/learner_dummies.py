"""Random entity observations with the layout of `engine.env.observation_types`, and their slot permutations,
for network tests that need no engine."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from impulse.engine.env.observation_types import (
    ATTENTION_CHANNELS,
    CIRCLE_FEATURES,
    JOINT_FEATURES,
    POLYGON_FEATURES,
    THRUSTER_FEATURES,
    EntityObservation,
)

SIZES = {"s": (5, 2, 1, 1), "m": (6, 3, 2, 2), "l": (12, 4, 6, 2)}  # polygons, circles, joints, thrusters
NUM_ARENA_POLYGONS = 4


def _one(rng: np.random.Generator, P: int, C: int, J: int, T: int) -> dict[str, np.ndarray]:
    N = P + C
    polygon_mask = np.concatenate([np.ones(NUM_ARENA_POLYGONS, bool), rng.random(P - NUM_ARENA_POLYGONS) < 0.7])
    circle_mask = rng.random(C) < 0.7
    polygon_mask[-1] = True  # at least one free polygon and one circle, so there is something to joint
    circle_mask[0] = True
    active = np.concatenate([polygon_mask, circle_mask])
    shapes = np.flatnonzero(active)

    joint_active = rng.random(J) < 0.7
    joint_active[0] = True
    ends = np.zeros((J, 2), np.int32)
    for j in np.flatnonzero(joint_active):
        ends[j] = rng.choice(shapes, 2, replace=False)
    # rows 0..J-1 read b->a (from b), rows J..2J-1 read a->b; (0, 0) for inactive joints
    joint_indexes = np.concatenate([ends[:, ::-1], ends]).astype(np.int32)
    joint_mask = np.concatenate([joint_active, joint_active])

    thruster_mask = rng.random(T) < 0.7
    thruster_mask[0] = True
    thruster_indexes = rng.choice(shapes, T).astype(np.int32)
    thruster_indexes[~thruster_mask] = rng.integers(0, N, (~thruster_mask).sum())  # not zeroed when inactive

    both = active[:, None] & active[None, :]
    one_hop = np.zeros((N, N), bool)
    for (f, t), on in zip(joint_indexes, joint_mask):
        one_hop[f, t] |= on
    one_hop[0, 0] = False
    component = one_hop | one_hop.T | np.eye(N, dtype=bool)
    contact = rng.random((N, N)) < 0.3
    attention = np.stack([both, component & both, one_hop & both, contact & both])

    return {
        "polygons": rng.normal(size=(P, POLYGON_FEATURES)),
        "circles": rng.normal(size=(C, CIRCLE_FEATURES)),
        "joints": rng.normal(size=(2 * J, JOINT_FEATURES)),
        "thrusters": rng.normal(size=(T, THRUSTER_FEATURES)),
        "polygon_mask": polygon_mask,
        "circle_mask": circle_mask,
        "joint_mask": joint_mask,
        "thruster_mask": thruster_mask,
        "joint_indexes": joint_indexes,
        "thruster_indexes": thruster_indexes,
        "attention_mask": attention,
    }


def dummy_observation(size: str, batch: tuple[int, ...] = (3,), seed: int = 0) -> EntityObservation:
    """A batch of random, internally consistent entity observations (leaves [*batch, ...]). Inactive rows carry
    random features, as nothing promises they are zero."""
    rng = np.random.default_rng(seed)
    P, C, J, T = SIZES[size]
    count = int(np.prod(batch, dtype=int))
    rows = [_one(rng, P, C, J, T) for _ in range(count)]
    fields = {}
    for name in rows[0]:
        stacked = np.stack([r[name] for r in rows]).reshape(batch + rows[0][name].shape)
        fields[name] = jnp.asarray(stacked.astype(np.float32) if stacked.dtype == np.float64 else stacked)
    assert fields["attention_mask"].shape[-3] == ATTENTION_CHANNELS
    return EntityObservation(**fields)


def permute_shapes(obs: EntityObservation, polygon_perm: np.ndarray, circle_perm: np.ndarray) -> EntityObservation:
    """The same scene with polygon slots reordered (new slot i holds old slot polygon_perm[i]) and likewise
    circles: features, masks and attention rows and columns move, body indices are renamed."""
    P = obs.polygons.shape[-2]
    order = np.concatenate([polygon_perm, P + circle_perm])  # new body i = old body order[i]
    rename = np.argsort(order)  # old body k is now new body rename[k]
    return obs.replace(
        polygons=obs.polygons[..., polygon_perm, :],
        circles=obs.circles[..., circle_perm, :],
        polygon_mask=obs.polygon_mask[..., polygon_perm],
        circle_mask=obs.circle_mask[..., circle_perm],
        joint_indexes=jnp.asarray(rename)[obs.joint_indexes],
        thruster_indexes=jnp.asarray(rename)[obs.thruster_indexes],
        attention_mask=obs.attention_mask[..., order, :][..., order],
    )


def scramble_inactive(obs: EntityObservation, seed: int = 1) -> EntityObservation:
    """The same scene with every inactive entity's features and attention entries replaced by other values."""
    rng = np.random.default_rng(seed)

    def noise(rows, mask):
        fresh = jnp.asarray(rng.normal(size=rows.shape) * 5.0, rows.dtype)
        return jnp.where(mask[..., None], rows, fresh)

    active = jnp.concatenate([obs.polygon_mask, obs.circle_mask], axis=-1)
    both = active[..., None, :, None] & active[..., None, None, :]
    random_attention = jnp.asarray(rng.random(obs.attention_mask.shape) < 0.5)
    return obs.replace(
        polygons=noise(obs.polygons, obs.polygon_mask),
        circles=noise(obs.circles, obs.circle_mask),
        joints=noise(obs.joints, obs.joint_mask),
        thrusters=noise(obs.thrusters, obs.thruster_mask),
        attention_mask=jnp.where(both, obs.attention_mask, random_attention),
    )
