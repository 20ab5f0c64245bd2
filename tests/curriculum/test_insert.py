"""`Curriculum.insert`: a level a person sends into a running curriculum takes an empty buffer slot, or the slot of
the lowest-scored level once the buffer is full, with the best buffered score (replayed soon) and no episodes."""

from __future__ import annotations

import jax
import numpy as np

from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods import make_curriculum
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels import handmade
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.levels.level import level_id_values


def test_insert_fills_empty_slots_then_replaces_the_lowest_score() -> None:
    curriculum = make_curriculum(CurriculumConfig(method="plr", buffer_size=3, noop_filter=False), EnvSpec(),
                            EnvParams(), 4)
    insert = jax.jit(curriculum.insert)
    state = jax.jit(curriculum.init)(jax.random.PRNGKey(0))
    names = ("s_easy_car_right", "s_hop_over", "s_lander", "s_catapult")
    levels = [load_kinetix_level(handmade.level_file(name), curriculum.spec.sizes).level for name in names]
    ids = [int(level_id_values(np.asarray(level.level_id)[None])[0]) for level in levels]
    slots = []
    for level in levels[:3]:
        state, slot = insert(state, level)
        slots.append(int(slot))
    assert slots == [0, 1, 2] and np.asarray(state.buffer.filled).all()
    state = state._replace(buffer=state.buffer._replace(score=np.asarray([0.5, 0.1, 0.9], np.float32),
                                                        episodes=np.asarray([4.0, 4.0, 4.0], np.float32)))
    state, slot = insert(state, levels[3])
    assert int(slot) == 1, "the lowest-scored level makes room"
    buffer = state.buffer
    assert level_id_values(np.asarray(buffer.levels.level_id)).tolist() == [ids[0], ids[3], ids[2]]
    assert np.asarray(buffer.score).tolist() == [0.5, np.float32(0.9), np.float32(0.9)]
    assert float(buffer.episodes[1]) == 0.0 and int(state.counters.inserted) == 4 and int(state.counters.evicted) == 1
