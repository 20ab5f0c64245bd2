"""The environment as a library (`impulse.make_env`, engine/env/api.py): the README's example runs as written, a
batch of environments under jit and vmap plays the set's levels and reports episodes, and bad arguments are clear
errors. The dynamics themselves are the engine's (tested beside it)."""

from __future__ import annotations

import re
import runpy

import jax
import numpy as np
import pytest

import impulse
from tests.support.paths import REPO


def test_the_example_runs_and_a_random_agent_finishes_and_solves_episodes(capsys: pytest.CaptureFixture[str]) -> None:
    runpy.run_path(str(REPO / "examples" / "random_agent.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "5 levels, actions multi_discrete (6,)" in out, out
    episodes, solved = (int(n) for n in re.search(r"(\d+) episodes finished, (\d+) solved", out).groups())
    # 64 environments for 256 steps: every one ends at least one episode; the hand-made set has easy levels
    assert episodes >= 64 and 0 < solved < episodes, out


def test_resets_draw_levels_of_the_set_with_the_key() -> None:
    env = impulse.make_env(levels="handmade", size="s")
    _, states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 32))
    started = {tuple(np.asarray(ids)) for ids in np.asarray(states.level.level_id)}
    known = {tuple(np.asarray(ids)) for ids in np.asarray(env.levels.level_id)}
    assert started <= known and len(started) > 1, "each reset draws one level of the set"


def test_bad_arguments_are_clear_errors() -> None:
    with pytest.raises(ValueError, match="fixed level set"):
        impulse.make_env(levels="random")
    with pytest.raises(ValueError, match=r"unknown option\(s\) frameskip; known: .*frame_skip"):
        impulse.make_env(frameskip=4)
    with pytest.raises(ValueError, match="unknown scene size 'xl'"):
        impulse.make_env(size="xl")
    with pytest.raises(ValueError, match="unknown observation 'rgb'"):
        impulse.make_env(observation="rgb")
