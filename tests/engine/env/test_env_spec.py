"""EnvSpec / EnvParams construction from the user-facing EnvConfig."""

from __future__ import annotations

import pytest

from impulse.engine.env.config import EnvConfig
from impulse.engine.env.spec import EnvParams, EnvSpec, env_from_config
from impulse.engine.physics import SIZE_M, SimParams


def test_env_from_config():
    config = EnvConfig(size="m", frame_skip=3, max_timesteps=100, dense_reward_scale=0.2, observation="symbolic",
                       action="discrete")
    spec, params = env_from_config(config)
    assert spec == EnvSpec(sizes=SIZE_M, frame_skip=3, max_timesteps=100, observation="symbolic", action="discrete")
    assert params.dense_reward_scale == 0.2 and params.sim == SimParams()
    hash(spec)  # a jit static argument
    assert EnvParams().dense_reward_scale == 0.1, "Kinetix's EnvParams default"


@pytest.mark.parametrize(
    "kwargs",
    [{"frame_skip": 0}, {"max_timesteps": 0}, {"observation": "rgb"}, {"action": "box"}, {"pixel_downscale": 3}],
)
def test_bad_spec_is_refused(kwargs):
    with pytest.raises(ValueError):
        EnvSpec(**kwargs)


def test_solver_setting_reaches_the_solver_options():
    spec, _ = env_from_config(EnvConfig(size="m", solver="jax2d"))
    assert spec.solver.schedule == "jax2d" and spec.sizes == SIZE_M
    assert env_from_config(EnvConfig())[0].solver.schedule == "phased"
