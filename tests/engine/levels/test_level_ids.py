"""Level ids: every level has a 64-bit id; files and hand-made levels hash their content, random levels draw one."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from impulse.engine.levels.kinetix_json import load_kinetix_level, save_kinetix_level
from impulse.engine.levels.level import (
    content_level_id,
    level_id_values,
    level_id_words,
    random_level_id,
    with_content_id,
)
from impulse.engine.levels.sets import load_level_set
from tests.support.level_samples import SIZES, random_levels


def test_words_and_values_round_trip_every_bit():
    for value in (1, 2**32 - 1, 2**32, 2**63 + 12345, 2**64 - 1):
        words = level_id_words(value)
        assert words.dtype == np.uint32
        assert int(level_id_values(words)) == value
    with pytest.raises(ValueError, match="64-bit"):
        level_id_words(2**64)


def test_hand_made_ids_are_content_hashes_distinct_and_stable():
    names, levels = load_level_set("handmade", SIZES["s"])
    ids = level_id_values(np.asarray(levels.level_id))
    assert len(set(ids.tolist())) == len(names) and 0 not in ids
    _, again = load_level_set("handmade", SIZES["s"])
    np.testing.assert_array_equal(level_id_values(np.asarray(again.level_id)), ids)
    one = jax.tree.map(lambda x: x[0], levels)
    nudged = one.replace(densities=one.densities.at[0].add(1.0))
    assert content_level_id(nudged) != content_level_id(one), "a changed level is a different level"
    assert content_level_id(with_content_id(one)) == int(ids[0]), "the id itself is not hashed"


def test_a_level_file_keeps_its_id_through_save_and_load(tmp_path):
    _, levels = load_level_set("handmade:s_easy_car_right", SIZES["s"])
    level = jax.tree.map(lambda x: x[0], levels)
    path = save_kinetix_level(tmp_path / "car.json", level, SIZES["s"])
    first = load_kinetix_level(path, SIZES["s"]).level
    second = load_kinetix_level(path, SIZES["s"]).level
    assert int(level_id_values(np.asarray(first.level_id))) != 0
    np.testing.assert_array_equal(np.asarray(first.level_id), np.asarray(second.level_id))


def test_random_levels_draw_distinct_deterministic_ids():
    levels = random_levels("s", 512, 3)
    ids = level_id_values(np.asarray(levels.level_id))
    assert len(set(ids.tolist())) == 512 and 0 not in ids
    np.testing.assert_array_equal(level_id_values(np.asarray(random_levels("s", 512, 3).level_id)), ids)
    assert int(level_id_values(np.asarray(random_level_id(jax.random.key(0))))) % 2 == 1, "never the unassigned 0"
