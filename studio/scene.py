"""A scene as JSON for the browser: the engine's drawable geometry (`engine.levels.drawing.SceneDrawing`) turned
into plain lists, so that the page draws exactly what the PNG renderer and Rerun draw (same colours, same rules)
without any geometry of its own.

World coordinates in metres, y up, the arena spanning [0, 5] x [0, 5]; colours as "#rrggbb"; numbers rounded to
0.1 mm, which keeps a frame of an L level to a few kilobytes. Each shape carries its global body index (`body`),
by which the editor names the shape it changes.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from impulse.engine.arena import ARENA_METRES
from impulse.engine.levels.drawing import SceneDrawing
from impulse.engine.levels.level import ROLE_NAMES, Level

DIGITS = 4


def _hex(colour: np.ndarray) -> str:
    r, g, b = (int(c) for c in colour)
    return f"#{r:02x}{g:02x}{b:02x}"


def _points(points: np.ndarray) -> list[list[float]]:
    return np.round(np.asarray(points, np.float64), DIGITS).reshape(-1, 2).tolist()


def _role(role: int) -> str:
    return ROLE_NAMES[role] if 0 <= role < len(ROLE_NAMES) else "neutral"


def scene_json(drawing: SceneDrawing) -> dict[str, Any]:
    """The drawing as a JSON-ready dict: `polygons` (body, points, colour, role, fixed), `circles` (body, centre,
    radius, mark: the rim point that shows the rotation, colour, role, fixed), `joints` (position, welded, colour,
    drive in [-1, 1]), `thrusters` (triangle, colour, drive in [0, 1]), each joint and thruster with its slot, and
    `arena` (its side in metres)."""
    polygons = [
        {"body": int(body), "points": _points(outline), "colour": _hex(colour), "role": _role(int(role)),
         "fixed": bool(fixed)}
        for body, outline, colour, role, fixed in zip(drawing.polygon_bodies, drawing.polygons,
                                                      drawing.polygon_colours, drawing.polygon_roles,
                                                      drawing.polygon_fixed, strict=True)
    ]
    circles = [
        {"body": int(body), "centre": _points(centre)[0], "radius": round(float(radius), DIGITS),
         "mark": _points(mark)[0], "colour": _hex(colour), "role": _role(int(role)), "fixed": bool(fixed)}
        for body, centre, radius, mark, colour, role, fixed in zip(
            drawing.circle_bodies, drawing.circle_centres, drawing.circle_radii, drawing.circle_marks,
            drawing.circle_colours, drawing.circle_roles, drawing.circle_fixed, strict=True)
    ]
    joints = [
        {"joint": int(slot), "position": _points(position)[0], "welded": bool(welded), "colour": _hex(colour),
         "drive": round(float(drive), 3)}
        for slot, position, welded, colour, drive in zip(drawing.joint_slots, drawing.joint_positions,
                                                         drawing.joint_welded, drawing.joint_colours,
                                                         drawing.joint_drive, strict=True)
    ]
    thrusters = [
        {"thruster": int(slot), "triangle": _points(triangle), "colour": _hex(colour),
         "drive": round(float(drive), 3)}
        for slot, triangle, colour, drive in zip(drawing.thruster_slots, drawing.thruster_triangles,
                                                 drawing.thruster_colours, drawing.thruster_drive, strict=True)
    ]
    return {"arena": ARENA_METRES, "polygons": polygons, "circles": circles, "joints": joints,
            "thrusters": thrusters}


def actuator_settings(level: Level) -> dict[str, list[dict[str, Any]]]:
    """What the editor's panel shows of each joint and thruster in `level` (host arrays): the joint's shapes, weld
    or motor (on, speed, power, limits in radians or None) and action binding; the thruster's shape, power, world
    direction (radians, at the level's start) and binding."""
    j, t = level.state.joints, level.state.thrusters
    joints = [
        {"joint": int(k), "a": int(j.a_index[k]), "b": int(j.b_index[k]), "weld": bool(j.is_fixed_joint[k]),
         "motor": bool(j.motor_on[k]), "speed": round(float(j.motor_speed[k]), DIGITS),
         "power": round(float(j.motor_power[k]), DIGITS),
         "limits": ([round(float(j.min_rotation[k]), DIGITS), round(float(j.max_rotation[k]), DIGITS)]
                    if j.motor_has_joint_limits[k] else None),
         "binding": int(level.motor_bindings[k])}
        for k in np.flatnonzero(np.asarray(j.active))
    ]
    thrusters = [
        {"thruster": int(k), "body": int(t.body_index[k]), "power": round(float(t.power[k]), DIGITS),
         "angle": round(float(t.rotation[k] + level.state.bodies.rotation[t.body_index[k]]), DIGITS),
         "binding": int(level.thruster_bindings[k])}
        for k in np.flatnonzero(np.asarray(t.active))
    ]
    return {"joints": joints, "thrusters": thrusters}
