"""The shapes of what the agent sees. Defined apart from the code that builds them so that networks (learner room)
can depend on the layout without depending on how it is computed.

Feature layouts follow Kinetix's entity and flat symbolic observations (see the Kinetix digest, section 7), so
that networks sized for Kinetix fit unchanged.
"""

from __future__ import annotations

import jax

from impulse.engine.pytree import pytree_dataclass

Array = jax.Array

POLYGON_FEATURES = 27  # 26 shape features + gravity_y / 10
CIRCLE_FEATURES = 19  # 18 shape features + gravity_y / 10
JOINT_FEATURES = 22  # 8 + 10 + number of motor bindings (4)
THRUSTER_FEATURES = 8  # 6 + number of thruster bindings (2)
ATTENTION_CHANNELS = 4  # all active shapes, same joint component, directly jointed, touching last step


@pytree_dataclass
class EntityObservation:
    """Per-entity feature rows with masks: the input of set and attention networks. Unbatched shapes shown."""

    polygons: Array  # [P, 27] all polygon slots, arena included
    circles: Array  # [C, 19]
    joints: Array  # [2J, 22] each joint twice: rows 0..J-1 read b->a, rows J..2J-1 read a->b
    thrusters: Array  # [T, 8]
    polygon_mask: Array  # [P] bool
    circle_mask: Array  # [C] bool
    joint_mask: Array  # [2J] bool
    thruster_mask: Array  # [T] bool
    joint_indexes: Array  # [2J, 2] int32 (from, to) body indices; (0, 0) for inactive joints
    thruster_indexes: Array  # [T] int32 body index
    attention_mask: Array  # [4, N, N] bool over bodies (polygons then circles)


@pytree_dataclass
class PixelObservation:
    """Kinetix's pixel observation: the scene drawn as an image, plus what the image cannot show. Unbatched
    shapes shown (125 = 500 / downscale at the default downscale 4)."""

    image: Array  # [W, H, 3] float32 in [0, 1], indexed [x, y] with y up
    global_info: Array  # [1] gravity_y / 10
