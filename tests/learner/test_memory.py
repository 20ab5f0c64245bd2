"""A training step that does not fit is refused after compiling, before it runs (learner/memory.py): XLA's own
account of the compiled program against the memory free, with the overrides that would fit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import pytest
from impulse.learner.memory import DoesNotFit, check_fits, free_bytes, program_bytes


@pytest.fixture(scope="module")
def compiled():
    def rollout(x):  # a scan whose stacked outputs are the "rollout buffer": 64 x 256 x 256 float32 = 16 MiB
        return jax.lax.scan(lambda c, _: (jnp.tanh(c), jnp.tanh(c)), x, None, length=64)

    return jax.jit(rollout).lower(jnp.ones((256, 256))).compile()


def test_the_compiled_programs_size_is_read_from_xla(compiled) -> None:
    need = program_bytes(compiled)
    assert need is not None and 16 * 2**20 <= need < 64 * 2**20, need
    assert free_bytes() > 2**20  # this machine has more than a megabyte free


def test_a_step_that_does_not_fit_is_refused_with_sizes_and_an_override(compiled) -> None:
    with pytest.raises(DoesNotFit, match=r"the training step needs about 0\.0 GiB \(2,048 envs x 256 steps per "
                                         r"update\).*use fewer, for example ppo.num_envs=\d+"):
        check_fits(compiled, "the training step", 2048, 256, free=4 * 2**20)
    check_fits(compiled, "the training step", 2048, 256, free=2**30)  # fits: no complaint
