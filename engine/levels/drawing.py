"""The geometry of one scene as things to draw, in world coordinates (pure numpy: any process, any renderer).

Every picture of a level comes from here: the PNG renderer (`impulse levels render`, `impulse curriculum inspect
--render`) and the Rerun views of live rollouts, evaluation episodes and the curriculum's gallery all draw a
`SceneDrawing`, so a level looks the same everywhere and the colour rules live in one place.

Colours follow Kinetix's renderer where it matters for reading a level: shapes in their role colour (green, blue,
red, neutral grey), fixed shapes (inverse mass 0) darker (neutral becomes dark grey, the other roles half as
bright); joints and thrusters in the colour of the action binding that drives them (white for joints without a
motor and for welded joints). Coordinates are metres with y up, the arena spanning [0, 5] x [0, 5].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from impulse.engine.levels.level import ROLE_NEUTRAL, Level
from impulse.engine.physics.state import SimState

Colour = tuple[int, int, int]
ROLE_COLOURS: tuple[Colour, ...] = (
    (160, 160, 160),  # neutral
    (0, 204, 0),  # green
    (0, 102, 204),  # blue
    (255, 102, 102),  # red
)
FIXED_NEUTRAL: Colour = (80, 80, 80)
UNBOUND: Colour = (255, 255, 255)
MOTOR_BINDING_COLOURS: tuple[Colour, ...] = ((255, 255, 0), (255, 0, 255), (0, 255, 255), (255, 153, 51))
THRUSTER_BINDING_COLOURS: tuple[Colour, ...] = MOTOR_BINDING_COLOURS[:2]
THRUSTER_LENGTH_METRES = 0.16


def shape_colour(role: int, fixed: bool) -> Colour:
    """Fill colour of a shape: its role colour, darker when the shape is fixed (inverse mass 0)."""
    role = int(role) if 0 <= int(role) < len(ROLE_COLOURS) else ROLE_NEUTRAL
    if not fixed:
        return ROLE_COLOURS[role]
    if role == ROLE_NEUTRAL:
        return FIXED_NEUTRAL
    r, g, b = ROLE_COLOURS[role]
    return r // 2, g // 2, b // 2


def _colours(pairs: list[Colour]) -> np.ndarray:
    return np.asarray(pairs, np.uint8).reshape(-1, 3)


def _rotation(angle: np.ndarray) -> np.ndarray:
    """[..., 2, 2] rotation matrices."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


@dataclass(frozen=True)
class SceneDrawing:
    """One scene's drawable parts, world coordinates (metres, y up). Only active slots appear; the arrays of a
    kind share their first axis."""

    polygons: tuple[np.ndarray, ...]
    """Outline of each polygon, [n, 2] vertices in order (not repeated at the end)."""
    polygon_colours: np.ndarray  # [p, 3] uint8
    polygon_roles: np.ndarray  # [p] int
    polygon_fixed: np.ndarray  # [p] bool
    circle_centres: np.ndarray  # [c, 2]
    circle_radii: np.ndarray  # [c]
    circle_marks: np.ndarray
    """[c, 2] the point on each circle's rim that shows its rotation (drawn as a spoke from the centre)."""
    circle_colours: np.ndarray  # [c, 3] uint8
    circle_roles: np.ndarray  # [c] int
    circle_fixed: np.ndarray  # [c] bool
    joint_positions: np.ndarray  # [j, 2] world anchor
    joint_welded: np.ndarray  # [j] bool
    joint_colours: np.ndarray  # [j, 3] uint8, by motor binding
    joint_drive: np.ndarray
    """[j] the motor command this step in [-1, 1] (0: idle, no motor, welded, or no action given)."""
    thruster_triangles: np.ndarray
    """[t, 3, 2] a small triangle at the thruster, its tip pointing the way it pushes."""
    thruster_directions: np.ndarray  # [t, 2] unit push direction
    thruster_colours: np.ndarray  # [t, 3] uint8, by thruster binding
    thruster_drive: np.ndarray  # [t] the thrust command this step in [0, 1] (0: off or no action given)
    polygon_bodies: np.ndarray
    """[p] the global body index of each polygon drawn (an editor picks shapes by it)."""
    circle_bodies: np.ndarray
    """[c] the global body index of each circle drawn (polygons first: num_polygons + circle slot)."""
    joint_slots: np.ndarray
    """[j] the joint slot of each joint drawn (an editor picks joints by it)."""
    thruster_slots: np.ndarray
    """[t] the thruster slot of each thruster drawn."""


def scene_drawing(level: Level, state: SimState | None = None, actuation: np.ndarray | None = None) -> SceneDrawing:
    """The drawable geometry of one (unbatched) `level`, in `state` if given (a state from a rollout; roles and
    bindings still come from `level`). `actuation` is the step's engine action per slot, [J + T]: each joint's
    motor command in [-1, 1], then each thruster's in [0, 1] (as `engine.env.actions.engine_actions` makes it)."""
    s = level.state if state is None else state
    if np.ndim(s.bodies.rotation) != 1:
        raise ValueError(f"scene_drawing draws one scene, got a batch of shape {np.shape(s.bodies.rotation)[:-1]}")
    roles = np.asarray(level.roles)
    position = np.asarray(s.bodies.position, np.float64)
    rotation = np.asarray(s.bodies.rotation, np.float64)
    active = np.asarray(s.bodies.active, bool)
    fixed = np.asarray(s.bodies.inverse_mass) == 0
    vertices = np.asarray(s.polygon_vertices, np.float64)
    n_vertices = np.clip(np.asarray(s.polygon_n_vertices), 0, vertices.shape[1])
    radius = np.asarray(s.circle_radius, np.float64)
    num_polygons = vertices.shape[0]
    turn = _rotation(rotation)  # [N, 2, 2]

    shown = [p for p in range(num_polygons) if active[p] and n_vertices[p] >= 3]
    polygons = tuple(position[p] + vertices[p, : n_vertices[p]] @ turn[p].T for p in shown)
    circles = np.asarray([num_polygons + c for c in range(radius.shape[0]) if active[num_polygons + c]], int)
    circle_radii = radius[circles - num_polygons]
    circle_centres = position[circles].reshape(-1, 2)
    circle_angle = rotation[circles]
    circle_marks = circle_centres + circle_radii[:, None] * np.stack([np.cos(circle_angle), np.sin(circle_angle)], -1)

    joints = s.joints
    num_joints = np.asarray(joints.active).shape[0]
    body_count = position.shape[0]
    a_index = np.asarray(joints.a_index)
    joint_ids = np.asarray([j for j in np.flatnonzero(np.asarray(joints.active)) if 0 <= a_index[j] < body_count], int)
    anchor_body = a_index[joint_ids]
    joint_positions = (position[anchor_body] + np.einsum(
        "jab,jb->ja", turn[anchor_body], np.asarray(joints.a_relative_pos, np.float64)[joint_ids])).reshape(-1, 2)
    welded = np.asarray(joints.is_fixed_joint, bool)[joint_ids]
    motorised = np.asarray(joints.motor_on, bool)[joint_ids] & ~welded
    motor_binding = np.asarray(level.motor_bindings)[joint_ids]
    joint_colours = _colours([MOTOR_BINDING_COLOURS[b] if m and 0 <= b < len(MOTOR_BINDING_COLOURS) else UNBOUND
                              for b, m in zip(motor_binding, motorised, strict=True)])

    thrusters = s.thrusters
    body_index = np.asarray(thrusters.body_index)
    thruster_ids = np.asarray([t for t in np.flatnonzero(np.asarray(thrusters.active))
                               if 0 <= body_index[t] < body_count], int)
    pushed = body_index[thruster_ids]
    bases = (position[pushed] + np.einsum("tab,tb->ta", turn[pushed], np.asarray(
        thrusters.relative_position, np.float64)[thruster_ids])).reshape(-1, 2)
    push_angle = rotation[pushed] + np.asarray(thrusters.rotation, np.float64)[thruster_ids]
    ahead = np.stack([np.cos(push_angle), np.sin(push_angle)], -1).reshape(-1, 2)
    side = np.stack([-ahead[:, 1], ahead[:, 0]], -1)
    length = THRUSTER_LENGTH_METRES
    triangles = np.stack([bases + ahead * 0.6 * length,
                          bases - ahead * 0.4 * length + side * 0.35 * length,
                          bases - ahead * 0.4 * length - side * 0.35 * length], 1)
    thruster_binding = np.asarray(level.thruster_bindings)[thruster_ids]
    thruster_colours = _colours([THRUSTER_BINDING_COLOURS[b] if 0 <= b < len(THRUSTER_BINDING_COLOURS) else UNBOUND
                                 for b in thruster_binding])

    joint_drive = np.zeros(joint_ids.size)
    thruster_drive = np.zeros(thruster_ids.size)
    if actuation is not None:
        actuation = np.asarray(actuation, np.float64)
        joint_drive = np.where(motorised, np.clip(actuation[joint_ids], -1.0, 1.0), 0.0)
        thruster_drive = np.clip(actuation[num_joints + thruster_ids], 0.0, 1.0)

    return SceneDrawing(
        polygons=polygons,
        polygon_colours=_colours([shape_colour(roles[p], fixed[p]) for p in shown]),
        polygon_roles=roles[np.asarray(shown, int)],
        polygon_fixed=fixed[np.asarray(shown, int)],
        circle_centres=circle_centres,
        circle_radii=circle_radii,
        circle_marks=circle_marks.reshape(-1, 2),
        circle_colours=_colours([shape_colour(roles[b], fixed[b]) for b in circles]),
        circle_roles=roles[circles],
        circle_fixed=fixed[circles],
        joint_positions=joint_positions,
        joint_welded=welded,
        joint_colours=joint_colours,
        joint_drive=joint_drive,
        thruster_triangles=triangles.reshape(-1, 3, 2),
        thruster_directions=ahead,
        thruster_colours=thruster_colours,
        thruster_drive=thruster_drive,
        polygon_bodies=np.asarray(shown, int),
        circle_bodies=circles,
        joint_slots=joint_ids,
        thruster_slots=thruster_ids,
    )
