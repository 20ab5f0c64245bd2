"""The hand-made levels: the registry, valid scenes, exported files that load back bit for bit, and scripted
controllers that solve the levels within an episode where doing nothing does not.

The controller runs compile once per size: every (level, controller) pair of a size is played in one vmapped
batch (`engine.env.play.play_batch`).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from impulse.engine.env.play import play_batch
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels import handmade
from impulse.engine.levels.handmade import controllers
from impulse.engine.levels.handmade.files import check, level_differences
from impulse.engine.levels.kinetix_json import load_kinetix_level
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, stack_levels
from impulse.engine.levels.sets import load_level_set
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S
from impulse.engine.physics.validate import validate_scene

NAMES = handmade.names()
MAX_STEPS = 256  # one Kinetix episode; frame skip 2 (EnvSpec's default)


def test_registry_spans_sizes_and_has_easy_levels():
    assert len(NAMES) >= 12
    for size in "sml":
        assert sum(handmade.LEVELS[n].size == size for n in NAMES) >= 3
    easy = [n for n in NAMES if "easy" in n and handmade.LEVELS[n].size == "s"]
    assert len(easy) >= 2
    for name in NAMES:
        entry = handmade.LEVELS[name]
        assert entry.name == name and entry.description and "\n" not in entry.description
        assert handmade.size_of(name) == entry.sizes
    with pytest.raises(KeyError, match="unknown hand-made level"):
        handmade.build("no_such_level")
    with pytest.raises(ValueError, match="does not fit"):
        handmade.build("l_claw", SIZE_S)


@pytest.mark.parametrize("name", NAMES)
def test_level_is_valid_and_has_a_task(name):
    entry = handmade.LEVELS[name]
    level = jax.tree.map(np.asarray, handmade.build(name))  # the checks below run in numpy
    assert validate_scene(level.state) == []
    active = np.asarray(level.state.bodies.active)
    roles = np.asarray(level.roles) * active
    assert (roles == ROLE_GREEN).any() and (roles == ROLE_BLUE).any()
    # Something is controllable, and every control has a sensible binding.
    joints, thrusters = level.state.joints, level.state.thrusters
    motors = np.asarray(joints.active & joints.motor_on & ~joints.is_fixed_joint)
    assert motors.any() or np.asarray(thrusters.active).any()
    assert set(np.asarray(level.motor_bindings)[motors]) <= {0, 1}
    assert set(np.asarray(level.thruster_bindings)[np.asarray(thrusters.active)]) <= {0, 1}
    # Green things move (or the level could not be solved by acting).
    green = np.flatnonzero(roles == ROLE_GREEN)
    assert (np.asarray(level.state.bodies.inverse_mass)[green] > 0).any()
    assert entry.sizes.num_bodies == active.shape[0]


@pytest.mark.parametrize("name", NAMES)
def test_exported_file_loads_back_identical(name):
    assert check(name) == []


def test_padded_build_matches_padded_file():
    """Building into a larger size gives what loading the exported file into that size gives."""
    for name, sizes in (("s_easy_car_right", SIZE_L), ("s_hop_over", SIZE_M), ("m_cartpole", SIZE_L)):
        built = handmade.build(name, sizes)
        loaded = load_kinetix_level(handmade.level_file(name), sizes).level
        assert level_differences(built, loaded) == [], name


def test_handmade_level_set_resolves():
    names, levels = load_level_set("handmade", SIZE_M)
    assert names == [n for n in NAMES if handmade.LEVELS[n].size in "sm"]
    assert levels.roles.shape == (len(names), SIZE_M.num_bodies)


def _play_size(size: str):
    """(names, solved/failed/steps under the scripted controller, the same under no-op) for one size."""
    names = [n for n in NAMES if handmade.LEVELS[n].size == size and n in controllers.SOLUTIONS]
    sizes = handmade.LEVELS[names[0]].sizes
    levels = stack_levels([handmade.build(n) for n in names] * 2)
    played = tuple(controllers.SOLUTIONS[n] for n in names) + (controllers.noop,)
    which = np.array(list(range(len(names))) + [len(names)] * len(names), np.int32)
    out = play_batch(EnvSpec(sizes=sizes), EnvParams(), levels, played, which, MAX_STEPS)
    out = jax.tree.map(np.asarray, out)
    k = len(names)
    return names, jax.tree.map(lambda x: x[:k], out), jax.tree.map(lambda x: x[k:], out)


@pytest.mark.parametrize("size", ["s", "m", "l"])
def test_scripted_controllers_solve_and_noop_does_not(size):
    names, scripted_out, noop_out = _play_size(size)
    assert len(names) >= 2
    for i, name in enumerate(names):
        assert scripted_out.solved[i] and not scripted_out.failed[i], (name, scripted_out.steps[i])
        assert scripted_out.steps[i] <= MAX_STEPS
        assert not noop_out.solved[i], name


def test_enough_levels_have_scripted_solutions():
    assert len(controllers.SOLUTIONS) >= 6
    assert set(controllers.SOLUTIONS) <= set(NAMES)
    assert {n for n in NAMES if "easy" in n} <= set(controllers.SOLUTIONS)
