"""A small imperative helper for writing hand-made levels: add shapes, joints and thrusters by world coordinates and
roles, then take the `Level`.

Shapes get Jax2D's mass convention (what Kinetix's files store and what its mutations recompute), so a mutated
hand-made level keeps its masses. Anchors are given in world coordinates and converted to each body's local frame.
Every helper checks that a slot was free, so a design that does not fit its size fails loudly when it is built.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from impulse.engine.levels.level import ROLE_NEUTRAL, Level, level_from_scene
from impulse.engine.physics.building import (
    add_circle,
    add_fixed_joint,
    add_polygon,
    add_revolute_joint,
    add_thruster,
    empty_scene,
    rectangle_vertices,
)
from impulse.engine.physics.sizes import SceneSizes

# Global indices of the arena polygons, which may carry roles like any shape (e.g. a red floor).
FLOOR, LEFT_WALL, RIGHT_WALL, CEILING = 0, 1, 2, 3


class SceneBuilder:
    """Builds one level of `sizes`; methods return the global body index (or the joint/thruster slot)."""

    def __init__(self, sizes: SceneSizes):
        self.sizes = sizes
        self.state = empty_scene(sizes)
        self.roles = np.zeros(sizes.num_bodies, np.int32)
        self.densities = np.ones(sizes.num_bodies, np.float32)
        self.motor_bindings = np.zeros(sizes.num_joints, np.int32)
        self.thruster_bindings = np.zeros(sizes.num_thrusters, np.int32)

    @staticmethod
    def _index(index, what: str) -> int:
        index = int(index)
        if index < 0:
            raise ValueError(f"no free {what} slot: the design does not fit its size")
        return index

    def _shape(self, index, role: int, density: float) -> int:
        index = self._index(index, "shape")
        self.roles[index] = role
        self.densities[index] = density
        return index

    def polygon(
        self,
        position,
        vertices,
        role: int = ROLE_NEUTRAL,
        rotation: float = 0.0,
        fixed: bool = False,
        density: float = 1.0,
        friction: float = 1.0,
        collision_mode: int = 1,
    ) -> int:
        """A convex polygon from clockwise local vertices around `position` (recentred on its centre of mass)."""
        self.state, index = add_polygon(
            self.state, position, np.asarray(vertices, np.float32), rotation=rotation, fixed=fixed, density=density,
            friction=friction, collision_mode=collision_mode, mass_convention="jax2d",
        )
        return self._shape(index, role, density)

    def rect(self, position, width: float, height: float, **kwargs) -> int:
        return self.polygon(position, rectangle_vertices(width, height), **kwargs)

    def circle(
        self,
        position,
        radius: float,
        role: int = ROLE_NEUTRAL,
        fixed: bool = False,
        density: float = 1.0,
        friction: float = 1.0,
        collision_mode: int = 1,
    ) -> int:
        self.state, index = add_circle(
            self.state, position, radius, fixed=fixed, density=density, friction=friction,
            collision_mode=collision_mode, mass_convention="jax2d",
        )
        return self._shape(index, role, density)

    def role(self, body: int, role: int) -> None:
        """Give an existing body (an arena polygon, say) a role."""
        self.roles[body] = role

    def local(self, body: int, world) -> np.ndarray:
        """A world point in `body`'s local frame."""
        b = self.state.bodies
        offset = np.asarray(world, np.float64) - np.asarray(b.position[body], np.float64)
        angle = -float(b.rotation[body])
        c, s = math.cos(angle), math.sin(angle)
        return np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]], np.float32)

    def hinge(
        self,
        a: int,
        b: int,
        anchor,
        motor: bool = False,
        speed: float = 1.0,
        power: float = 1.0,
        binding: int = 0,
        limits: tuple[float, float] | None = None,
    ) -> int:
        """A revolute joint at world point `anchor`. With a motor, action +1 drives b's spin relative to a
        counter-clockwise (so a wheel given as `b` on a chassis `a` rolls left; give the wheel as `a` to roll
        right on +1)."""
        self.state, slot = add_revolute_joint(
            self.state, a, b, self.local(a, anchor), self.local(b, anchor), motor_on=motor, motor_speed=speed,
            motor_power=power, has_joint_limits=limits is not None,
            min_rotation=-math.pi if limits is None else limits[0],
            max_rotation=math.pi if limits is None else limits[1],
        )
        slot = self._index(slot, "joint")
        self.motor_bindings[slot] = binding
        return slot

    def weld(self, a: int, b: int, anchor) -> int:
        """A fixed joint at world point `anchor`, keeping the current relative angle."""
        self.state, slot = add_fixed_joint(self.state, a, b, self.local(a, anchor), self.local(b, anchor))
        return self._index(slot, "joint")

    def thruster(
        self, body: int, direction: float, power: float, at=None, binding: int = 0
    ) -> int:
        """A thruster on `body` pushing along world angle `direction` (radians; 0 = +x, pi/2 = up) as placed,
        mounted at world point `at` (default: the body's centre of mass, so it exerts no torque)."""
        b = self.state.bodies
        rel = (0.0, 0.0) if at is None else self.local(body, at)
        rotation = direction - float(b.rotation[body])
        self.state, slot = add_thruster(self.state, body, rel, rotation, power)
        slot = self._index(slot, "thruster")
        self.thruster_bindings[slot] = binding
        return slot

    def level(self) -> Level:
        return level_from_scene(
            self.state,
            roles=jnp.asarray(self.roles),
            densities=jnp.asarray(self.densities),
            motor_bindings=jnp.asarray(self.motor_bindings),
            thruster_bindings=jnp.asarray(self.thruster_bindings),
        )
