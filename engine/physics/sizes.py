"""Static scene sizes: everything that changes array shapes and therefore forces a recompile."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Solver = Literal["phased", "jax2d", "jax2d_wipe"]
SOLVERS: tuple[str, ...] = ("phased", "jax2d", "jax2d_wipe")
Backend = Literal["xla", "pallas", "pallas_interpret"]
BACKENDS: tuple[str, ...] = ("xla", "pallas", "pallas_interpret")


@dataclass(frozen=True)
class SceneSizes:
    """Slot counts of a scene. Hashable, so it can be a static argument of jitted functions.

    The first `num_static_polygons` polygons are the arena (floor, left wall, right wall, ceiling) by convention.
    Polygons carry up to `max_polygon_vertices` vertices; raising it is a size change, not a code change.
    `solver` picks the contact schedule (static, so it is compiled in): "phased" (default, fastest) or "jax2d"
    (Jax2D's batch order, for trajectories that follow Jax2D's closely; see docs/engine.md) or "jax2d_wipe" (the
    same plus Jax2D's padding bug, which zeroes the last contact pair's impulses; only to compare trajectories
    with Jax2D and Kinetix, never to train with).
    `backend` picks how the phased solver iterations run: "xla" (the pure-JAX stages) or "pallas" (one fused
    kernel per block of scenes on a GPU, solver_kernel.py; the XLA stages on other platforms);
    "pallas_interpret" runs that kernel through Pallas's interpreter on any platform, to test it without a GPU.
    """

    num_polygons: int = 5
    num_circles: int = 2
    num_joints: int = 1
    num_thrusters: int = 1
    max_polygon_vertices: int = 4
    num_static_polygons: int = 4
    num_solver_iterations: int = 10
    warm_starting: bool = True
    solver: Solver = "phased"
    backend: Backend = "xla"

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
        if self.solver not in SOLVERS:
            raise ValueError(f"unknown solver {self.solver!r}; choose one of {', '.join(SOLVERS)}")
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown physics backend {self.backend!r}; choose one of {', '.join(BACKENDS)}")
        if self.backend != "xla" and self.solver != "phased":
            raise ValueError(f"physics backend {self.backend!r} runs the phased solver only, not {self.solver!r}")
        if self.num_solver_iterations < 1:
            raise ValueError(f"num_solver_iterations must be >= 1, got {self.num_solver_iterations}")

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


def size_preset(name: str) -> SceneSizes:
    """The Kinetix size called `name` ("s", "m" or "l", case-insensitive)."""
    try:
        return _PRESETS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown scene size {name!r}; choose one of s, m, l") from None
