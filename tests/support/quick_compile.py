"""Compiling for tests: programs that a test compiles itself and then runs only briefly.

On a CPU most of such a test's time goes to XLA compiling: the curriculum's `sample`, a rollout of the physics
engine or a network's gradient take 10 to 60 CPU seconds to compile and then run for well under a second. At
backend optimisation level 0 (the code XLA generates is not optimised by LLVM) the same programs compile in about
40% less time and run a few times slower, the better trade for a test; what they compute is the same (up to
floating-point rounding). Only for the jits a test makes itself: what the code under test compiles (an actor's
rollout, the learner's update) keeps the settings it runs with in a real run.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax

QUICK_COMPILE = {"xla_backend_optimization_level": 0}


def quick_jit(fun: Callable[..., Any], **jit_kwargs: Any) -> Any:
    """`jax.jit(fun, **jit_kwargs)`, compiled with QUICK_COMPILE."""
    return jax.jit(fun, compiler_options=QUICK_COMPILE, **jit_kwargs)
