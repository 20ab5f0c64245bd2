"""Content validation of decoded messages against what the receiver was built for."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from impulse.bus.codec import TREE_HASH_META, Kind, Message, Rejected, decode, encode, tree_hash
from impulse.bus.schema import ArraySpec, Schema, check

RUN = "schema-run"


def trajectory(steps: int = 4, envs: int = 3, **replace: Any) -> dict[str, np.ndarray]:
    arrays = {
        "obs/shapes": np.zeros((steps, envs, 4), np.float32),
        "obs/joints": np.zeros((steps, envs, 2, 3), np.float32),
        "action": np.zeros((steps, envs, 6), np.int8),
        "reward": np.zeros((steps, envs), np.float32),
        "level_id": np.zeros((steps, envs), np.int64),
    }
    arrays.update(replace)
    return arrays


SCHEMA = Schema.from_example(Kind.TRAJECTORY, trajectory(), leading=("T", "E"), finite=("obs", "reward", "level_id"))


def message(arrays: dict[str, np.ndarray], kind: Kind = Kind.TRAJECTORY, **meta: Any) -> Message:
    return decode(encode(kind, arrays, run=RUN, meta=meta), run=RUN)


def refused(msg: Message, schema: Schema, reason: str, dims: dict[str, int] | None = None) -> str:
    with pytest.raises(Rejected) as info:
        check(msg, schema, dims)
    assert info.value.reason == reason, info.value
    return info.value.detail


def test_from_example_names_leading_dims_and_finite_arrays() -> None:
    assert SCHEMA.arrays["obs/joints"] == ArraySpec(np.dtype(np.float32), ("T", "E", 2, 3), finite=True)
    assert SCHEMA.arrays["action"] == ArraySpec(np.dtype(np.int8), ("T", "E", 6), finite=False)
    assert SCHEMA.arrays["level_id"].finite  # listed, though an int array is finite by nature
    assert SCHEMA.arrays["obs/shapes"].describe() == "(T, E, 4)"
    nested = Schema.from_example(Kind.WEIGHTS, {"dense": {"w": np.zeros((2, 2))}}, finite=True)
    assert nested.arrays == {"dense/w": ArraySpec(np.dtype(np.float64), (2, 2), finite=True)}
    with pytest.raises(ValueError, match="match no array"):
        Schema.from_example(Kind.TRAJECTORY, trajectory(), finite=("observations",))
    with pytest.raises(ValueError, match="fewer than the leading"):
        Schema.from_example(Kind.TRAJECTORY, {"x": np.zeros(3)}, leading=("T", "E"))
    with pytest.raises(ValueError, match="non-negative"):
        ArraySpec(np.dtype(np.float32), (-1,))
    with pytest.raises(ValueError, match="cannot be sent"):
        ArraySpec(np.dtype(np.complex64), (1,))


def test_a_fitting_message_passes_and_binds_its_dims() -> None:
    extra = {"new_in_minor_version": np.zeros(2)}
    assert check(message(trajectory(steps=16, envs=8, **extra)), SCHEMA) == {"T": 16, "E": 8}
    assert check(message(trajectory(steps=16, envs=8)), SCHEMA, dims={"E": 8}) == {"T": 16, "E": 8}


def test_missing_array() -> None:
    arrays = trajectory()
    del arrays["reward"]
    assert "'reward' is missing" in refused(message(arrays), SCHEMA, "schema")


def test_wrong_dtype() -> None:
    detail = refused(message(trajectory(reward=np.zeros((4, 3), np.float64))), SCHEMA, "bad_dtype")
    assert detail == "array 'reward' has dtype float64, expected float32"


def test_wrong_shapes() -> None:
    detail = refused(message(trajectory(**{"obs/shapes": np.zeros((3, 4), np.float32)})), SCHEMA, "bad_shape")
    assert detail == "array 'obs/shapes' has shape (3, 4), expected (T, E, 4)"
    detail = refused(message(trajectory(**{"obs/shapes": np.zeros((4, 3, 5), np.float32)})), SCHEMA, "bad_shape")
    assert detail == "array 'obs/shapes' has shape (4, 3, 5), expected (T, E, 4)"


def test_inconsistent_or_pinned_named_dims() -> None:
    detail = refused(message(trajectory(reward=np.zeros((5, 3), np.float32))), SCHEMA, "bad_shape")
    assert "'reward'" in detail and "T=4" in detail and "'obs/shapes'" in detail
    detail = refused(message(trajectory(envs=3)), SCHEMA, "bad_shape", dims={"E": 256})
    assert "E=256" in detail and "the receiver" in detail


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values(bad: float) -> None:
    reward = np.zeros((4, 3), np.float32)
    reward[2, 1] = bad
    assert "'reward' holds 1 NaN/Inf" in refused(message(trajectory(reward=reward)), SCHEMA, "non_finite")
    not_required = Schema.from_example(Kind.TRAJECTORY, trajectory(), leading=("T", "E"))
    assert check(message(trajectory(reward=reward)), not_required) == {"T": 4, "E": 3}


def test_tree_hash_and_kind() -> None:
    weights = {"w": np.ones((3, 2), np.float32)}
    schema = Schema.from_example(Kind.WEIGHTS, weights, finite=True, tree_hash=tree_hash(weights))
    assert check(message(weights, Kind.WEIGHTS, **{TREE_HASH_META: tree_hash(weights)}), schema) == {}
    other = {"w": np.ones((2, 3), np.float32)}
    refused(message(weights, Kind.WEIGHTS, **{TREE_HASH_META: tree_hash(other)}), schema, "tree_hash")
    refused(message(weights, Kind.WEIGHTS), schema, "tree_hash")
    refused(message(weights, Kind.TRAJECTORY, **{TREE_HASH_META: tree_hash(weights)}), schema, "wrong_kind")
