"""GPU selection by config: positions among the GPUs a process may see become its CUDA_VISIBLE_DEVICES."""

from __future__ import annotations

import pytest

from impulse.deploy.config import ConfigError, resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.devices import VISIBLE, restrict_gpus, visible_gpus


def test_positions_are_gpu_numbers_when_nothing_is_inherited() -> None:
    assert visible_gpus([2], None) == "2"
    assert visible_gpus([0, 3], "") == "0,3"


def test_positions_index_the_gpus_a_scheduler_handed_out() -> None:
    assert visible_gpus([1], "4,5,6") == "5"
    assert visible_gpus([2, 0], "4, 5,6") == "6,4"
    with pytest.raises(ValueError, match="shows only 3 GPU"):
        visible_gpus([3], "4,5,6")


def test_restrict_sets_the_variable_only_when_asked() -> None:
    environ: dict[str, str] = {VISIBLE: "1,2"}
    assert restrict_gpus([], environ) is None and environ[VISIBLE] == "1,2"
    assert restrict_gpus([1], environ) == "2" and environ[VISIBLE] == "2"


@pytest.mark.parametrize("override", ["learner.devices=[0,0]", "actors.devices=[-1]", "learner.devices=[true]",
                                      "curriculum.devices=[0,1]", "curriculum.devices=[-2]"])
def test_bad_device_lists_are_named(override: str) -> None:
    with pytest.raises(ConfigError, match=override.split("=")[0]):
        resolve_config(RunConfig, None, [override])


def test_device_lists_load() -> None:
    config = resolve_config(RunConfig, None, ["learner.devices=[0,1]", "actors.devices=[2,3]",
                                                "curriculum.devices=[1]"])
    assert config.learner.devices == (0, 1) and config.actors.devices == (2, 3) and config.curriculum.devices == (1,)
