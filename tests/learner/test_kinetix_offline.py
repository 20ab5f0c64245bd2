"""Kinetix offline datasets (learner/kinetix_offline.py): the fixture written by Kinetix's own environment
in its behaviour-cloning format (benchmarks/_reference_offline_dataset.py) reads back as our levels, whose
symbolic observations match Kinetix's, with the same actions, masks, steps and episode ends; malformed datasets
give errors that name the dataset and the problem."""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from impulse.engine.env.observations import observe
from impulse.engine.env.spec import EnvSpec
from impulse.engine.levels.kinetix_json import LevelFileError
from impulse.engine.physics.sizes import SIZE_S, SceneSizes
from impulse.learner.kinetix_offline import (
    KinetixTransitions,
    kinetix_offline_observations,
    read_kinetix_offline,
)

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "kinetix" / "offline"
GROUPS = ("flat", "traj")
# One bound observation function for every call, so its compiled batch function is shared.
SYMBOLIC = functools.partial(observe, EnvSpec(sizes=SIZE_S, observation="symbolic"))


def _fixture_missing() -> str | None:
    """Why the fixture tests cannot run, or None."""
    if not (FIXTURE / "expected.npz").is_file():
        return f"Kinetix offline fixture not found at {FIXTURE} (made by benchmarks/_reference_offline_dataset.py)"
    if importlib.util.find_spec("numcodecs") is None:
        return "numcodecs (installed with zarr) is needed to decompress the fixture's Blosc chunks"
    return None


needs_fixture = pytest.mark.skipif(_fixture_missing() is not None, reason=_fixture_missing() or "")


@pytest.fixture(scope="module")
def expected() -> dict[str, np.ndarray]:
    with np.load(FIXTURE / "expected.npz") as data:
        return {key: data[key] for key in data.files}


@pytest.fixture(scope="module")
def transitions() -> dict[str, KinetixTransitions]:
    return {group: read_kinetix_offline(FIXTURE / group, SIZE_S) for group in GROUPS}


@needs_fixture
@pytest.mark.parametrize("group", GROUPS)
def test_observations_and_actions_match_kinetix(
    group: str, transitions: dict[str, KinetixTransitions], expected: dict[str, np.ndarray]
) -> None:
    data = transitions[group]
    want = expected[f"{group}/observation"]
    assert data.levels.roles.shape == (len(want), SIZE_S.num_bodies)
    got = np.asarray(kinetix_offline_observations(data, SYMBOLIC))
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(data.action, expected[f"{group}/action"])
    np.testing.assert_array_equal(data.action_mask, expected[f"{group}/action_mask"])
    np.testing.assert_array_equal(data.timestep, expected[f"{group}/timestep"])
    assert data.mask.all()


@needs_fixture
def test_flat_and_trajectory_variants(
    transitions: dict[str, KinetixTransitions], expected: dict[str, np.ndarray]
) -> None:
    flat, traj = transitions["flat"], transitions["traj"]
    assert flat.done is None and flat.trajectory_length is None
    assert traj.trajectory_length == 10
    np.testing.assert_array_equal(traj.done, expected["traj/done"])
    # Each trajectory's steps come in order, from the episode's first step.
    steps = traj.timestep.reshape(-1, traj.trajectory_length)
    np.testing.assert_array_equal(steps, np.broadcast_to(np.arange(traj.trajectory_length), steps.shape))


@needs_fixture
def test_state_too_large_for_sizes_names_the_record() -> None:
    one_circle = SceneSizes(num_polygons=5, num_circles=1, num_joints=1, num_thrusters=1)
    with pytest.raises(LevelFileError) as caught:
        read_kinetix_offline(FIXTURE / "traj", one_circle)
    message = str(caught.value)
    assert "shard shard_000, trajectory 0, step 0" in message and "too large" in message and "circles" in message


def _zarr_v2_group(path: Path, records: np.ndarray) -> Path:
    zarr = pytest.importorskip("zarr")
    group = zarr.open_group(str(path), mode="w", zarr_format=2)
    shard = group.create_array("shard_000", shape=records.shape, dtype=records.dtype, chunks=(2,))
    shard[:] = records
    return path


def test_shard_missing_fields(tmp_path: Path) -> None:
    records = np.ones(3, np.dtype([("mask", "?"), ("env_state/timestep", "<i4")]))
    dataset = _zarr_v2_group(tmp_path / "partial", records)
    with pytest.raises(LevelFileError) as caught:
        read_kinetix_offline(dataset, SIZE_S)
    message = str(caught.value)
    assert str(dataset) in message and "shard shard_000" in message
    assert "action" in message and "env_state/polygon/position" in message and "missing" in message


def test_not_a_zarr_group(tmp_path: Path) -> None:
    with pytest.raises(LevelFileError, match="not a zarr group: no .zgroup"):
        read_kinetix_offline(tmp_path, SIZE_S)
    with pytest.raises(LevelFileError, match="no such folder"):
        read_kinetix_offline(tmp_path / "absent", SIZE_S)
    (tmp_path / "file.json").write_text("{}")
    with pytest.raises(LevelFileError, match="not a folder"):
        read_kinetix_offline(tmp_path / "file.json", SIZE_S)
    zarr = pytest.importorskip("zarr")
    zarr.open_group(str(tmp_path / "v3"), mode="w", zarr_format=3)
    with pytest.raises(LevelFileError, match="zarr format 3"):
        read_kinetix_offline(tmp_path / "v3", SIZE_S)
    _zarr_v2_group(tmp_path / "empty", np.zeros(0, np.dtype([("mask", "?")])))
    with pytest.raises(LevelFileError, match="every shard is empty"):
        read_kinetix_offline(tmp_path / "empty", SIZE_S)
