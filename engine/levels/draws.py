"""Named random draws: the uniform numbers a generator or a mutation consumes, each under a name.

Level generation follows Kinetix's procedure draw for draw, so the order in which uniforms are consumed is part of
the behaviour (the same key must give the same level). A `DrawLayout` states that order once, as the fields of a
NamedTuple, and splits a flat vector of uniforms into them, so the code that uses the numbers reads
`draws.rotation` rather than `u[4]`, and the count to draw (`layout.size`) cannot drift from the fields.

Fields are scalars unless given a width, in which case they are vectors of that width (even a width of 1, so a
field sized by the scene, such as one draw per free slot, keeps its axis).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, NamedTuple, TypeVar

import jax

Array = jax.Array
Draws = TypeVar("Draws", bound=NamedTuple)


@dataclass(frozen=True)
class DrawLayout(Generic[Draws]):
    """The uniforms of one random decision, in the order they are consumed: `draws` names them (a NamedTuple
    class), `widths` gives the vector fields their lengths."""

    draws: type[Draws]
    widths: Mapping[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        unknown = set(self.widths) - set(self.draws._fields)
        if unknown:
            raise ValueError(f"{self.draws.__name__} has no field(s) {sorted(unknown)}")
        negative = {name: width for name, width in self.widths.items() if width < 0}
        if negative:
            raise ValueError(f"negative draw widths {negative}")

    @property
    def size(self) -> int:
        """How many uniforms the layout consumes."""
        return sum(self.widths.get(name, 1) for name in self.draws._fields)

    def split(self, uniforms: Array) -> Draws:
        """`uniforms` [>= size] (any extra at the end ignored) as the named draws."""
        if uniforms.shape[-1] < self.size:
            raise ValueError(f"{self.draws.__name__} needs {self.size} uniforms, got {uniforms.shape[-1]}")
        parts: dict[str, Any] = {}
        start = 0
        for name in self.draws._fields:
            if name in self.widths:
                parts[name] = uniforms[..., start : start + self.widths[name]]
                start += self.widths[name]
            else:
                parts[name] = uniforms[..., start]
                start += 1
        return self.draws(**parts)
