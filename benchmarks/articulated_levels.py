"""Articulated test levels: chains of bodies joined by motorised revolute joints, with no contact between the
chain's own bodies (jointed bodies never collide), in the style of Kinetix's MuJoCo-like L levels (walkers,
swimmers, hoppers). They exist to compare our joints and motors with Jax2D's on multi-joint chains
(`impulse bench compat_jax2d --levels "$PWD/benchmarks/levels/articulated/*.json"`).

Each level is written as a Kinetix level file into ``benchmarks/levels/articulated/`` (committed; rerun this
script after changing it). What varies: the number of bodies (2 in S, 3 in M, 3 to 6 in L), boxes or wheels as
links, motors on most joints, joint limits on or off, a fixed root (an arm held in the air) or a free root (the
chain lying or standing on the floor) or a free chain dropped from the air. Gravity is Kinetix's (its file loader
ignores a file's gravity, so a weightless swimmer cannot be compared through it). The chain's last body is green
and a small blue disc sits out of reach, so the files are valid levels.

    python -m impulse.benchmarks.articulated_levels [--out DIR]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from impulse.engine.levels.kinetix_json import save_kinetix_level
from impulse.engine.levels.level import ROLE_BLUE, ROLE_GREEN, level_from_scene
from impulse.engine.physics.building import add_circle, add_rectangle, add_revolute_joint, empty_scene
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes

OUT = Path(__file__).resolve().parent / "levels" / "articulated"
LINK_LENGTH = 0.6
LINK_HEIGHT = 0.16
FLOOR_TOP = 0.4
"""Height of the arena floor's top face; a chain on the floor starts just above it (1 cm)."""
ON_FLOOR = FLOOR_TOP + LINK_HEIGHT / 2 + 0.01


@dataclass(frozen=True)
class Chain:
    """One articulated level: `links` bodies in a row from `root` (x, y), each `LINK_LENGTH` long."""

    name: str
    sizes: SceneSizes
    links: int
    root: tuple[float, float]
    fixed_root: bool = False
    limits: bool = False
    wheels: bool = False
    """Circles instead of boxes for the links after the first (S and M have few polygon slots)."""
    unmotored: tuple[int, ...] = ()
    """Joints (0-based along the chain) left without a motor."""
    angle: float = 0.0
    """The chain's direction from the root (radians; 0 along +x, pi/2 straight up)."""
    motor_speed: float = 2.0
    motor_power: float = 1.0


CHAINS = (
    Chain("s_box_wheel", SIZE_S, 2, (2.0, FLOOR_TOP + LINK_HEIGHT + 0.01), wheels=True),
    Chain("s_arm_fixed", SIZE_S, 2, (2.5, 2.5), fixed_root=True, wheels=True, limits=True),
    Chain("m_three_wheels", SIZE_M, 3, (1.5, FLOOR_TOP + LINK_HEIGHT + 0.01), wheels=True),
    Chain("m_arm_fixed_limits", SIZE_M, 3, (2.0, 3.0), fixed_root=True, wheels=True, limits=True),
    Chain("l_dropped_3", SIZE_L, 3, (1.5, 2.5)),
    Chain("l_dropped_5", SIZE_L, 5, (1.0, 2.5), limits=True),
    Chain("l_crawler_4", SIZE_L, 4, (1.0, ON_FLOOR)),
    Chain("l_crawler_6_limits", SIZE_L, 6, (0.6, ON_FLOOR), limits=True, unmotored=(4,)),
    Chain("l_arm_3_fixed", SIZE_L, 3, (1.5, 3.5), fixed_root=True),
    Chain("l_arm_4_fixed_limits", SIZE_L, 4, (1.0, 3.5), fixed_root=True, limits=True),
    Chain("l_arm_6_fixed", SIZE_L, 6, (0.8, 3.8), fixed_root=True, unmotored=(1,)),
    Chain("l_hopper_3", SIZE_L, 3, (2.5, FLOOR_TOP + LINK_LENGTH * 0.45 + 0.01), angle=np.pi / 2, limits=True),
    Chain("l_walker_5", SIZE_L, 5, (1.2, ON_FLOOR), limits=True, motor_power=2.0),
    Chain("l_strong_arm_5", SIZE_L, 5, (1.0, 3.0), fixed_root=True, motor_speed=4.0, motor_power=3.0),
)


def build(chain: Chain):
    """The chain's level: its scene, roles and motor bindings (joint i is driven by motor key i % 4)."""
    state = empty_scene(chain.sizes)
    direction = np.array([np.cos(chain.angle), np.sin(chain.angle)], np.float32)
    bodies = []
    for i in range(chain.links):
        centre = np.asarray(chain.root, np.float32) + direction * (i * LINK_LENGTH)
        if chain.wheels and i > 0:
            state, body = add_circle(state, tuple(centre), LINK_HEIGHT)
        else:
            state, body = add_rectangle(state, tuple(centre), LINK_LENGTH * 0.9, LINK_HEIGHT, rotation=chain.angle,
                                        fixed=chain.fixed_root and i == 0)
        assert int(body) >= 0, f"{chain.name}: no free slot for link {i}"
        bodies.append(int(body))
    half = LINK_LENGTH / 2
    for j, (a, b) in enumerate(zip(bodies[:-1], bodies[1:])):
        b_anchor = (0.0, 0.0) if chain.wheels else (-half, 0.0)
        state, joint = add_revolute_joint(
            state, a, b, (half, 0.0), b_anchor, motor_on=j not in chain.unmotored, motor_speed=chain.motor_speed,
            motor_power=chain.motor_power, has_joint_limits=chain.limits, min_rotation=-0.8, max_rotation=0.8,
        )
        assert int(joint) >= 0, f"{chain.name}: no free joint slot for joint {j}"
    state, target = add_circle(state, (4.5, 4.5), 0.1, fixed=True)
    roles = np.zeros(chain.sizes.num_bodies, np.int32)
    roles[bodies[-1]] = ROLE_GREEN
    roles[int(target)] = ROLE_BLUE
    bindings = np.arange(chain.sizes.num_joints, dtype=np.int32) % 4
    return level_from_scene(state, roles=roles, motor_bindings=bindings)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for chain in CHAINS:
        path = save_kinetix_level(args.out / f"{chain.name}.json", build(chain), chain.sizes, SimParams())
        print(path)


if __name__ == "__main__":
    main()
