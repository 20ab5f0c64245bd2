"""Static scene sizes: the slot counts, everything that changes array shapes and therefore forces a recompile.

How the step solves a scene (schedule, backend, iterations, warm start) is not a size: see `options.py`.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SceneSizes:
    """Slot counts of a scene. Hashable, so it can be a static argument of jitted functions.

    The first `num_static_polygons` polygons are the arena (floor, left wall, right wall, ceiling) by convention.
    Polygons carry up to `max_polygon_vertices` vertices; raising it is a size change, not a code change.
    """

    num_polygons: int = 5
    num_circles: int = 2
    num_joints: int = 1
    num_thrusters: int = 1
    max_polygon_vertices: int = 4
    num_static_polygons: int = 4

    def __post_init__(self) -> None:
        if self.num_polygons < self.num_static_polygons:
            raise ValueError(
                f"num_polygons ({self.num_polygons}) must be at least num_static_polygons "
                f"({self.num_static_polygons}): the arena polygons occupy the first slots"
            )
        for name in ("num_circles", "num_joints", "num_thrusters", "num_static_polygons"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.max_polygon_vertices < 3:
            raise ValueError(f"max_polygon_vertices must be >= 3, got {self.max_polygon_vertices}")

    @property
    def num_bodies(self) -> int:
        return self.num_polygons + self.num_circles

    def fits_in(self, other: SceneSizes) -> bool:
        """Whether a scene of these sizes can be padded into `other`'s slots."""
        return (
            self.num_polygons <= other.num_polygons
            and self.num_circles <= other.num_circles
            and self.num_joints <= other.num_joints
            and self.num_thrusters <= other.num_thrusters
            and self.max_polygon_vertices <= other.max_polygon_vertices
            and self.num_static_polygons == other.num_static_polygons
        )


# Kinetix's three environment sizes (polygons incl. the 4 arena polygons, circles, joints, thrusters).
SIZE_S = SceneSizes(num_polygons=5, num_circles=2, num_joints=1, num_thrusters=1)
SIZE_M = SceneSizes(num_polygons=6, num_circles=3, num_joints=2, num_thrusters=2)
SIZE_L = SceneSizes(num_polygons=12, num_circles=4, num_joints=6, num_thrusters=2)

_PRESETS = {"s": SIZE_S, "m": SIZE_M, "l": SIZE_L}
SIZE_NAMES = tuple(_PRESETS)
"""The names `size_preset` knows, smallest first."""


def size_preset(name: str) -> SceneSizes:
    """The Kinetix size called `name` ("s", "m" or "l", case-insensitive)."""
    try:
        return _PRESETS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown scene size {name!r}; choose one of s, m, l") from None
