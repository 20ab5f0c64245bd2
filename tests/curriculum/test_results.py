"""Per-level results from a [T, E] window, against a hand-computed example: episodes are split at `done`, each
episode's value-based inputs are means over its steps, and episodes are summed per level id."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from impulse.curriculum.results import level_results, results_from_host, results_to_host
from impulse.engine.levels.level import level_id_values, level_id_words


def test_episodes_are_tallied_per_level_id_with_per_episode_means():
    # Two environments over 4 steps. Env 0 plays level 7 for 2 steps (solved), then level 9 for 2 steps (not
    # done). Env 1 plays level 9 for 3 steps (failed), then level 7 for 1 step (done, solved).
    seven, nine = level_id_words(7), level_id_words(9)
    ids = np.array([[seven, nine], [seven, nine], [nine, nine], [nine, seven]], np.uint32)
    done = np.array([[0, 0], [1, 0], [0, 1], [0, 1]], bool)
    solved = np.array([[0, 0], [1, 0], [0, 0], [0, 1]], bool)
    ret = np.array([[0, 0], [1.0, 0], [0, -1.0], [0, 2.0]], np.float32)
    value = np.array([[1, 2], [3, 4], [5, 6], [7, 8]], np.float32)
    advantage = np.array([[1, -1], [-3, 2], [5, 3], [7, -4]], np.float32)
    got = results_to_host(level_results(jnp.asarray(ids), jnp.asarray(done), jnp.asarray(solved), jnp.asarray(ret),
                                        jnp.asarray(value), jnp.asarray(advantage), 5, rows=4))
    by_id = {int(i): k for k, i in enumerate(level_id_values(got["level_id"]))}
    assert set(by_id) == {7, 9}
    k7, k9 = by_id[7], by_id[9]
    assert (got["episodes"][k7], got["solved"][k7]) == (2, 2)  # env 0's first episode and env 1's second
    assert (got["episodes"][k9], got["solved"][k9]) == (1, 0)  # env 1's first; env 0's second has not ended
    assert got["return_sum"][k7] == pytest.approx(3.0) and got["return_max"][k7] == pytest.approx(2.0)
    assert got["return_max"][k9] == pytest.approx(-1.0)
    # Level 7: episode (values 1, 3; advantages 1, -3) and episode (value 8; advantage -4).
    assert got["value_sum"][k7] == pytest.approx(2.0 + 8.0)
    assert got["pvl_sum"][k7] == pytest.approx(0.5 + 0.0)
    assert got["l1_sum"][k7] == pytest.approx(2.0 + 4.0)
    # Level 9: env 1's steps 0-2 (values 2, 4, 6; advantages -1, 2, 3).
    assert got["value_sum"][k9] == pytest.approx(4.0)
    assert got["pvl_sum"][k9] == pytest.approx(5.0 / 3.0)
    assert got["l1_sum"][k9] == pytest.approx(2.0)
    assert (got["policy_version"] == 5).all()

    padded = results_from_host(got, 6)
    assert int(np.asarray(padded.valid).sum()) == 2 and int(np.asarray(padded.episodes).sum()) == 3


def test_results_of_several_frames_pack_into_full_chunks_in_their_order():
    from impulse.curriculum.wire import results_chunks

    def frame(first_id: int, count: int) -> dict[str, np.ndarray]:
        ids = np.stack([level_id_words(first_id + i) for i in range(count)]).astype(np.uint32)
        counts = np.arange(1, count + 1, dtype=np.int32)
        zeros = np.zeros(count, np.float32)
        return {"level_id": ids, "episodes": counts, "solved": counts - 1, "return_sum": zeros, "return_max": zeros,
                "value_sum": zeros, "pvl_sum": zeros, "l1_sum": zeros, "policy_version": np.full(count, 2, np.int32)}

    chunks = results_chunks([frame(10, 3), frame(20, 3), frame(30, 1)], rows=4)
    assert [int(np.asarray(c.valid).sum()) for c in chunks] == [4, 3]
    ids = [int(i) for c in chunks for i in level_id_values(np.asarray(c.level_id))[np.asarray(c.valid)]]
    assert ids == [10, 11, 12, 20, 21, 22, 30]
    assert [int(e) for c in chunks for e in np.asarray(c.episodes)[np.asarray(c.valid)]] == [1, 2, 3, 1, 2, 3, 1]
    assert results_chunks([], rows=4) == []
