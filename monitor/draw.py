"""Drawing a scene into a Rerun recording: the same `SceneDrawing` the PNG renderer draws, as 2D primitives.

One scene is a handful of entities under its path, so a view can show or hide each kind:

    <path>/polygons   LineStrips2D  closed outlines, role colours
    <path>/circles    Points2D      discs with the circles' radii, role colours
    <path>/spokes     LineStrips2D  centre to rim, showing each circle's rotation
    <path>/joints     Points2D      binding colours; a driven motor draws larger, labelled with its command
    <path>/thrusters  LineStrips2D  closed triangles pointing the way they push, binding colours
    <path>/flames     Arrows2D      behind each firing thruster, as long as its thrust

Rerun's 2D views put y down (image convention) and our world has y up, so points are logged as
(x, ARENA - y): the arena is the square [0, 5] x [0, 5] in the view, the floor at the bottom. `log_scene` logs
every entity every time, empty when a kind is absent, so a level with fewer parts does not leave stale ones of
the previous level on screen.
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from impulse.engine.arena import ARENA_METRES
from impulse.engine.levels.drawing import SceneDrawing

OUTLINE_RADIUS = 0.025
SPOKE_RADIUS = 0.015
JOINT_RADIUS = 0.05
DRIVEN_JOINT_RADIUS = 0.09
FLAME_LENGTH = 0.25
FLAME_COLOUR = (255, 120, 0)
SCENE_PARTS = ("polygons", "circles", "spokes", "joints", "thrusters", "flames")


def to_view(points: np.ndarray) -> np.ndarray:
    """World (x, y up) to Rerun 2D view coordinates (x, y down), any leading shape."""
    points = np.asarray(points, np.float32)
    return np.stack([points[..., 0], ARENA_METRES - points[..., 1]], -1)


def _closed(outline: np.ndarray) -> np.ndarray:
    return to_view(np.concatenate([outline, outline[:1]], 0))


def scene_archetypes(drawing: SceneDrawing) -> dict[str, rr.AsComponents]:
    """The Rerun archetype of each part of the scene (`SCENE_PARTS`), keyed by part name."""
    driven = np.abs(drawing.joint_drive) > 0
    firing = drawing.thruster_drive > 0
    tails = (drawing.thruster_triangles[:, 1] + drawing.thruster_triangles[:, 2]) / 2
    flame = -drawing.thruster_directions * (drawing.thruster_drive * FLAME_LENGTH)[:, None]
    return {
        "polygons": rr.LineStrips2D([_closed(p) for p in drawing.polygons], colors=drawing.polygon_colours,
                                    radii=OUTLINE_RADIUS),
        "circles": rr.Points2D(to_view(drawing.circle_centres.reshape(-1, 2)), radii=drawing.circle_radii,
                               colors=drawing.circle_colours),
        "spokes": rr.LineStrips2D([to_view(np.stack([c, m])) for c, m in zip(drawing.circle_centres,
                                                                              drawing.circle_marks, strict=True)],
                                  colors=drawing.circle_colours // 2, radii=SPOKE_RADIUS),
        "joints": rr.Points2D(to_view(drawing.joint_positions.reshape(-1, 2)),
                              radii=np.where(driven, DRIVEN_JOINT_RADIUS, JOINT_RADIUS),
                              colors=drawing.joint_colours,
                              labels=[f"{d:+.0f}" if on else "" for d, on in zip(drawing.joint_drive, driven,
                                                                                  strict=True)]),
        "thrusters": rr.LineStrips2D([_closed(t) for t in drawing.thruster_triangles],
                                     colors=drawing.thruster_colours, radii=SPOKE_RADIUS),
        "flames": rr.Arrows2D(origins=to_view(tails[firing].reshape(-1, 2)),
                              vectors=flame[firing].reshape(-1, 2) * [1.0, -1.0],  # a direction: only y flips
                              colors=[FLAME_COLOUR] * int(firing.sum()), radii=SPOKE_RADIUS),
    }


def log_scene(recording: rr.RecordingStream, path: str, drawing: SceneDrawing, *, static: bool = False) -> None:
    """Log every part of `drawing` under `path` at the recording's current time (or as static data)."""
    for part, archetype in scene_archetypes(drawing).items():
        recording.log(f"{path}/{part}", archetype, static=static)
