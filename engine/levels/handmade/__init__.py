"""Impulse's own hand-made levels: a registry of name -> (size, one-line description, builder).

The designs live in `designs` (Python builders, the source of truth); `python -m engine.levels.handmade.build`
exports each one as a Kinetix JSON file next to this module (`<name>.json`), so Kinetix and other tools can load
them too. `controllers` holds controllers that solve some of them (played by `engine.env.play`), used by the
tests.

    from impulse.engine.levels import handmade
    handmade.names()                       # all level names, S first
    level = handmade.build("s_easy_car_right")             # in its own size
    level = handmade.build("s_easy_car_right", SIZE_L)     # padded into a larger size

Levels whose name contains "easy" are meant to be learnable by a small PPO agent in a couple of CPU minutes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from impulse.engine.levels.handmade import designs
from impulse.engine.levels.level import Level, with_content_id
from impulse.engine.physics.sizes import SceneSizes, size_preset

LEVEL_DIR = Path(__file__).resolve().parent


@dataclass(frozen=True)
class HandmadeLevel:
    name: str
    size: str  # "s", "m" or "l": the smallest Kinetix size the design fits
    description: str
    builder: Callable[[SceneSizes], Level]

    @property
    def sizes(self) -> SceneSizes:
        return size_preset(self.size)

    @property
    def path(self) -> Path:
        """The exported Kinetix JSON file."""
        return LEVEL_DIR / f"{self.name}.json"


def _entry(size: str, description: str, builder: Callable[[SceneSizes], Level]) -> tuple[str, HandmadeLevel]:
    return builder.__name__, HandmadeLevel(builder.__name__, size, description, builder)


LEVELS: dict[str, HandmadeLevel] = dict(
    [
        _entry("s", "Very easy: hold the thruster to push the green box right into the blue ball.",
               designs.s_easy_thrust_right),
        _entry("s", "Very easy: drive the motorised green wheel right (motor +1) into the blue ball.",
               designs.s_easy_car_right),
        _entry("s", "Thrust aiming: a short diagonal burst hops the green box over the red ball onto the blue one.",
               designs.s_hop_over),
        _entry("s", "Lander: pulse the slanted thruster so the falling green pod drifts onto the blue pad, not the "
               "red floor.", designs.s_lander),
        _entry("s", "Catapult: swing the motorised arm to fling the green ball onto the blue ball before it drops "
               "onto the red floor.", designs.s_catapult),
        _entry("m", "Locomotion: drive the two-wheel car over a bump until its green body touches the raised blue "
               "ball.", designs.m_car_bump),
        _entry("m", "Thrust aiming: climb (thruster 0), then cross above the red shelf (thruster 1) to the blue ball, "
               "below a red one.", designs.m_thrust_shelf),
        _entry("m", "Balance: push the cart with two thrusters, keeping its pole up, until the green tip touches the "
               "blue ball.", designs.m_cartpole),
        _entry("m", "Catapult: swing the arm just hard enough to land the green ball on the blue ledge, not the red "
               "floor.", designs.m_catapult),
        _entry("l", "Locomotion: drive the green car up a ramp and across a gap over the red floor to the blue ball.",
               designs.l_car_climb),
        _entry("l", "Lander: steer the legged green craft with two tilted jets over a red tower onto the blue pad.",
               designs.l_lander),
        _entry("l", "Balance: roll the wheeled cart, keeping its pole up, until the green tip touches the blue ball.",
               designs.l_cartpole),
        _entry("l", "Catapult: fling the green ball over a red wall onto the blue ledge.", designs.l_catapult),
        _entry("l", "Grasping: close the claw on the green ball (motor 1), swing it over (motor 0) and open it above "
               "the blue bin.", designs.l_claw),
    ]
)


def names() -> list[str]:
    """All hand-made level names, in registry order (S, then M, then L)."""
    return list(LEVELS)


def _get(name: str) -> HandmadeLevel:
    try:
        return LEVELS[name]
    except KeyError:
        raise KeyError(f"unknown hand-made level {name!r}; available: {', '.join(LEVELS)}") from None


def size_of(name: str) -> SceneSizes:
    """The smallest Kinetix size the level fits."""
    return _get(name).sizes


def description(name: str) -> str:
    return _get(name).description


def build(name: str, sizes: SceneSizes | None = None) -> Level:
    """The level built into `sizes` (default: its own size; a larger size adds inactive slots), with its content
    hash as its id, as when its exported file is loaded."""
    entry = _get(name)
    target = entry.sizes if sizes is None else sizes
    if not entry.sizes.fits_in(target):
        raise ValueError(f"hand-made level {name} (size {entry.size.upper()}) does not fit the requested sizes")
    return with_content_id(entry.builder(target))


def level_file(name: str) -> Path:
    """The level's exported Kinetix JSON file (written by `python -m engine.levels.handmade.build`)."""
    return _get(name).path
