"""Named draws: a layout consumes uniforms in its fields' order, so naming them changed no generated level."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import pytest

from impulse.engine.levels.draws import DrawLayout
from impulse.engine.levels.generator import SHAPE_ADD_DRAWS, SHAPE_DRAWS, THRUSTER_DRAWS


class Example(NamedTuple):
    first: jax.Array
    pair: jax.Array
    per_slot: jax.Array
    last: jax.Array


def test_fields_take_their_widths_in_order() -> None:
    layout = DrawLayout(Example, {"pair": 2, "per_slot": 1})
    assert layout.size == 5
    draws = layout.split(jnp.arange(6.0))  # one spare at the end is ignored
    assert float(draws.first) == 0.0 and draws.first.shape == ()
    assert draws.pair.tolist() == [1.0, 2.0]
    assert draws.per_slot.shape == (1,)  # a width of one keeps its axis
    assert float(draws.last) == 4.0
    batched = layout.split(jnp.arange(10.0).reshape(2, 5))
    assert batched.pair.shape == (2, 2) and batched.last.tolist() == [4.0, 9.0]


def test_bad_layouts_and_short_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="no field"):
        DrawLayout(Example, {"pairs": 2})
    with pytest.raises(ValueError, match="needs 4 uniforms"):
        DrawLayout(Example).split(jnp.zeros(3))


def test_generator_layouts_keep_kinetix_draw_counts() -> None:
    """The counts the generator consumed before its draws had names: a change here changes every level."""
    assert (SHAPE_DRAWS.size, SHAPE_ADD_DRAWS.size, THRUSTER_DRAWS.size) == (5, 28, 10)
