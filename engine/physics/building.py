"""Building scenes: the empty arena, the slot writers, and helpers that add shapes, joints and thrusters.

The writers (`write_body`, `write_polygon`, `write_circle`, `write_joint`, `write_thruster`) set one slot to a new
active entry, or nothing for slot -1; every scene that is built, by these helpers or by the level generator
(`engine.levels.generator`), is written through them, so a slot is filled the same way everywhere.

Each helper is a pure function of the state (jittable; the slot used is the first inactive one, and the slot
index is returned), so the level generator can build scenes on the device. A full array is reported by the
validator rather than silently ignored: the helpers return index -1 when no slot is free.
"""

from __future__ import annotations

from typing import TypeVar

import jax.numpy as jnp
import numpy as np

from impulse.engine.physics.mass import MassConvention, circle_mass_properties, polygon_mass_properties
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import Bodies, ContactCache, Joints, SimState, Thrusters

Array = jnp.ndarray
SlotTable = TypeVar("SlotTable", Bodies, Joints, Thrusters)

FLOOR_TOP = 0.4


def _arena_polygons(max_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions and clockwise local vertices of floor, left wall, right wall and ceiling (Kinetix's files)."""
    def box(half_w: float, half_h: float) -> list[tuple[float, float]]:
        return [(-half_w, half_h), (half_w, half_h), (half_w, -half_h), (-half_w, -half_h)]

    positions = np.array([[2.5, -4.8], [0.0, 0.0], [0.0, 0.0], [2.5, 10.2]], dtype=np.float32)
    vertices = np.zeros((4, max_vertices, 2), dtype=np.float32)
    vertices[0, :4] = box(2.5, 5.2)
    vertices[1, :4] = [(-5.0, 5.0), (0.0, 5.0), (0.0, 0.0), (-5.0, 0.0)]
    vertices[2, :4] = [(5.0, 5.0), (10.0, 5.0), (10.0, 0.0), (5.0, 0.0)]
    vertices[3, :4] = box(2.5, 5.2)
    return positions, vertices


def empty_scene(sizes: SceneSizes, arena: bool = True) -> SimState:
    """A scene with every slot free except the static arena polygons (floor top at y = 0.4, walls at x = 0 and
    x = 5, ceiling at y = 5). With `arena=False` the arena slots exist but are inactive (an empty, open world)."""
    P, C, J, T = sizes.num_polygons, sizes.num_circles, sizes.num_joints, sizes.num_thrusters
    N, V, S = P + C, sizes.max_polygon_vertices, sizes.num_static_polygons
    tables = pair_tables(sizes)
    f32 = lambda *shape: jnp.zeros(shape, jnp.float32)  # noqa: E731
    position = np.zeros((N, 2), np.float32)
    vertices = np.zeros((P, V, 2), np.float32)
    n_vertices = np.full((P,), min(4, V), np.int32)
    mode = np.ones((N,), np.int32)
    active = np.zeros((N,), bool)
    if S:
        arena_pos, arena_vertices = _arena_polygons(V)
        count = min(S, 4)
        position[:count] = arena_pos[:count]
        vertices[:count] = arena_vertices[:count]
        mode[:S] = 2
        active[:S] = arena
    bodies = Bodies(
        position=jnp.asarray(position),
        rotation=f32(N),
        velocity=f32(N, 2),
        angular_velocity=f32(N),
        inverse_mass=f32(N),
        inverse_inertia=f32(N),
        friction=jnp.ones((N,), jnp.float32),
        restitution=f32(N),
        collision_mode=jnp.asarray(mode),
        active=jnp.asarray(active),
    )
    joints = Joints(
        a_index=jnp.zeros((J,), jnp.int32),
        b_index=jnp.zeros((J,), jnp.int32),
        a_relative_pos=f32(J, 2),
        b_relative_pos=f32(J, 2),
        rotation=f32(J),
        active=jnp.zeros((J,), bool),
        is_fixed_joint=jnp.zeros((J,), bool),
        motor_on=jnp.zeros((J,), bool),
        motor_speed=jnp.ones((J,), jnp.float32),
        motor_power=jnp.ones((J,), jnp.float32),
        motor_has_joint_limits=jnp.zeros((J,), bool),
        min_rotation=jnp.full((J,), -np.pi, jnp.float32),
        max_rotation=jnp.full((J,), np.pi, jnp.float32),
        acc_impulse=f32(J, 2),
        acc_r_impulse=f32(J),
        global_position=f32(J, 2),
    )
    thrusters = Thrusters(
        body_index=jnp.zeros((T,), jnp.int32),
        relative_position=f32(T, 2),
        rotation=f32(T),
        power=jnp.ones((T,), jnp.float32),
        active=jnp.zeros((T,), bool),
        global_position=f32(T, 2),
    )
    K = tables.num_contacts
    return SimState(
        bodies=bodies,
        polygon_vertices=jnp.asarray(vertices),
        polygon_n_vertices=jnp.asarray(n_vertices),
        circle_radius=f32(C),
        joints=joints,
        thrusters=thrusters,
        contacts=ContactCache(f32(K), f32(K), jnp.zeros((K,), bool)),
        pair_collides=jnp.ones((tables.num_pairs,), bool),
        gravity=jnp.asarray([0.0, -9.81], jnp.float32),
    )


def _free_slot(active: Array) -> Array:
    """First inactive slot, or -1 when all are taken."""
    if active.shape[0] == 0:
        return jnp.asarray(-1, jnp.int32)
    slot = jnp.argmin(active).astype(jnp.int32)
    return jnp.where(active[slot], -1, slot)


def put_rows(old: Array, hot: Array, new) -> Array:
    """`old` with the rows where `hot` (shape old.shape[:1]) is true replaced by `new` (broadcast to a row).

    A select rather than a scatter: under vmap (the generator builds thousands of scenes at once) it stays an
    elementwise operation, and a slot of -1 simply matches no row."""
    mask = hot.reshape(hot.shape + (1,) * (old.ndim - 1))
    return jnp.where(mask, jnp.asarray(new, old.dtype), old)


def write_slot(table: SlotTable, slot: Array, **values) -> SlotTable:
    """`table` (a scene's bodies, joints or thrusters) with the fields named in `values` written into `slot` and
    the slot made active; fields not named keep the slot's values. Slot -1 writes nothing."""
    hot = jnp.arange(table.active.shape[0]) == slot
    values["active"] = True
    return table.replace(**{name: put_rows(getattr(table, name), hot, value) for name, value in values.items()})


def write_body(
    bodies: Bodies,
    index: Array,
    *,
    position: Array,
    rotation,
    inverse_mass: Array,
    inverse_inertia: Array,
    velocity=(0.0, 0.0),
    angular_velocity=0.0,
    friction=1.0,
    restitution=0.0,
    collision_mode=1,
) -> Bodies:
    """A new active body in slot `index` (a global body index: polygons first); index -1 writes nothing. Its shape
    goes in with `write_polygon` or `write_circle`."""
    return write_slot(
        bodies, index, position=position, rotation=rotation, velocity=velocity, angular_velocity=angular_velocity,
        inverse_mass=inverse_mass, inverse_inertia=inverse_inertia, friction=friction, restitution=restitution,
        collision_mode=collision_mode,
    )


def write_polygon(state: SimState, index: Array, vertices: Array, n_vertices) -> SimState:
    """The shape of polygon `index`: `n_vertices` clockwise local vertices, padded to the size's maximum (index -1
    writes nothing)."""
    hot = jnp.arange(state.polygon_vertices.shape[0]) == index
    return state.replace(
        polygon_vertices=put_rows(state.polygon_vertices, hot, vertices),
        polygon_n_vertices=put_rows(state.polygon_n_vertices, hot, n_vertices),
    )


def write_circle(state: SimState, circle: Array, radius) -> SimState:
    """The radius of circle slot `circle` (its body index minus the polygon count; -1 writes nothing)."""
    hot = jnp.arange(state.circle_radius.shape[0]) == circle
    return state.replace(circle_radius=put_rows(state.circle_radius, hot, radius))


def write_joint(joints: Joints, slot: Array, **fields) -> Joints:
    """A new active joint in `slot` with the given fields (the others keep the slot's values); -1 writes nothing.
    The collision filter is the caller's to refresh (`refresh_collision_filter`)."""
    return write_slot(joints, slot, **fields)


def write_thruster(
    thrusters: Thrusters, slot: Array, *, body_index, relative_position, rotation, power, global_position
) -> Thrusters:
    """A new active thruster in `slot` on body `body_index`; -1 writes nothing."""
    return write_slot(
        thrusters, slot, body_index=body_index, relative_position=relative_position, rotation=rotation, power=power,
        global_position=global_position,
    )


def add_polygon(
    state: SimState,
    position,
    vertices,
    rotation: float = 0.0,
    velocity=(0.0, 0.0),
    angular_velocity: float = 0.0,
    density: float = 1.0,
    friction: float = 1.0,
    restitution: float = 0.0,
    collision_mode: int = 1,
    fixed: bool = False,
    mass_convention: MassConvention = "physical",
) -> tuple[SimState, Array]:
    """Add a convex polygon given by clockwise local vertices around `position`; it is recentred on its centre of
    mass. Returns (state, body index), index -1 if all polygon slots are in use."""
    num_polygons, max_vertices = state.polygon_vertices.shape[:2]
    verts = jnp.asarray(vertices, jnp.float32)
    n = verts.shape[0]
    if not 3 <= n <= max_vertices:
        raise ValueError(f"a polygon needs 3 to {max_vertices} vertices, got {n}")
    padded = jnp.zeros((max_vertices, 2), jnp.float32).at[:n].set(verts)
    centre, local, inverse_mass, inverse_inertia = polygon_mass_properties(
        padded, n, jnp.asarray(density, jnp.float32), mass_convention
    )
    if fixed:
        inverse_mass, inverse_inertia = jnp.zeros_like(inverse_mass), jnp.zeros_like(inverse_inertia)
    # Arena slots are never reused: pairs among them are not enumerated, so shapes there could not collide.
    first = arena_polygon_count(state)
    slot = _free_slot(state.bodies.active[first:num_polygons])
    slot = jnp.where(slot < 0, -1, slot + first)
    world_centre = jnp.asarray(position, jnp.float32) + _rotate_point(rotation, centre)
    bodies = write_body(
        state.bodies, slot, position=world_centre, rotation=rotation, velocity=jnp.asarray(velocity, jnp.float32),
        angular_velocity=angular_velocity, inverse_mass=inverse_mass, inverse_inertia=inverse_inertia,
        friction=friction, restitution=restitution, collision_mode=collision_mode,
    )
    return write_polygon(state.replace(bodies=bodies), slot, local, n), slot


def _rotate_point(angle, point: Array) -> Array:
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * point[0] - s * point[1], s * point[0] + c * point[1]])


def rectangle_vertices(width: float, height: float) -> np.ndarray:
    """Clockwise from the top-left corner, centred on the origin."""
    hw, hh = width / 2.0, height / 2.0
    return np.array([[-hw, hh], [hw, hh], [hw, -hh], [-hw, -hh]], dtype=np.float32)


def add_rectangle(state: SimState, position, width: float, height: float, **kwargs) -> tuple[SimState, Array]:
    return add_polygon(state, position, rectangle_vertices(width, height), **kwargs)


def add_circle(
    state: SimState,
    position,
    radius: float,
    rotation: float = 0.0,
    velocity=(0.0, 0.0),
    angular_velocity: float = 0.0,
    density: float = 1.0,
    friction: float = 1.0,
    restitution: float = 0.0,
    collision_mode: int = 1,
    fixed: bool = False,
    mass_convention: MassConvention = "physical",
) -> tuple[SimState, Array]:
    """Add a disc. Returns (state, body index) where body index = num_polygons + circle slot, or -1 if full."""
    num_polygons = state.polygon_vertices.shape[0]
    inverse_mass, inverse_inertia = circle_mass_properties(
        jnp.asarray(radius, jnp.float32), jnp.asarray(density, jnp.float32), mass_convention
    )
    if fixed:
        inverse_mass, inverse_inertia = jnp.zeros_like(inverse_mass), jnp.zeros_like(inverse_inertia)
    slot = _free_slot(state.bodies.active[num_polygons:])
    index = jnp.where(slot < 0, -1, slot + num_polygons)
    bodies = write_body(
        state.bodies, index, position=jnp.asarray(position, jnp.float32), rotation=rotation,
        velocity=jnp.asarray(velocity, jnp.float32), angular_velocity=angular_velocity, inverse_mass=inverse_mass,
        inverse_inertia=inverse_inertia, friction=friction, restitution=restitution, collision_mode=collision_mode,
    )
    return write_circle(state.replace(bodies=bodies), slot, radius), index


def _add_joint(
    state: SimState, a_index, b_index, a_relative_pos, b_relative_pos, rotation, **fields
) -> tuple[SimState, Array]:
    """A joint in the first free slot, at rest (no accumulated impulse), holding `rotation` (None: the bodies'
    current relative angle) as its reference; `fields` say which kind. Refreshes the collision filter."""
    if rotation is None:
        rotation = state.bodies.rotation[b_index] - state.bodies.rotation[a_index]
    slot = _free_slot(state.joints.active)
    joints = write_joint(
        state.joints, slot, a_index=a_index, b_index=b_index, a_relative_pos=jnp.asarray(a_relative_pos, jnp.float32),
        b_relative_pos=jnp.asarray(b_relative_pos, jnp.float32), rotation=rotation, acc_impulse=jnp.zeros(2),
        acc_r_impulse=0.0, **fields,
    )
    return refresh_collision_filter(state.replace(joints=joints)), slot


def add_revolute_joint(
    state: SimState,
    a_index,
    b_index,
    a_relative_pos,
    b_relative_pos,
    motor_on: bool = False,
    motor_speed: float = 1.0,
    motor_power: float = 1.0,
    has_joint_limits: bool = False,
    min_rotation: float = -np.pi,
    max_rotation: float = np.pi,
    rotation=None,
) -> tuple[SimState, Array]:
    """Pin two bodies together at their anchors, letting them rotate relative to each other.

    `rotation` is the reference relative angle that limits are measured from; by default the current one
    (Jax2D's helper leaves it at 0, so limits silently depend on how the bodies were placed).
    """
    return _add_joint(
        state, a_index, b_index, a_relative_pos, b_relative_pos, rotation, is_fixed_joint=False, motor_on=motor_on,
        motor_speed=motor_speed, motor_power=motor_power, motor_has_joint_limits=has_joint_limits,
        min_rotation=min_rotation, max_rotation=max_rotation,
    )


def add_fixed_joint(
    state: SimState, a_index, b_index, a_relative_pos, b_relative_pos, rotation=None
) -> tuple[SimState, Array]:
    """Weld two bodies; they keep the relative angle `rotation` (by default the current one)."""
    return _add_joint(
        state, a_index, b_index, a_relative_pos, b_relative_pos, rotation, is_fixed_joint=True, motor_on=False,
        motor_has_joint_limits=False,
    )


def add_thruster(
    state: SimState, body_index, relative_position=(0.0, 0.0), rotation: float = 0.0, power: float = 1.0
) -> tuple[SimState, Array]:
    """Attach a thruster to a body; with action 1 it pushes along `rotation` (body frame) at `power` times the
    base thruster power."""
    slot = _free_slot(state.thrusters.active)
    body = state.bodies
    rel = jnp.asarray(relative_position, jnp.float32)
    angle = body.rotation[body_index]
    world = body.position[body_index] + _rotate_point(angle, rel)
    new = write_thruster(
        state.thrusters, slot, body_index=body_index, relative_position=rel, rotation=rotation, power=power,
        global_position=world,
    )
    return state.replace(thrusters=new), slot


def connected_by_joints(joints: Joints, num_bodies: int) -> Array:
    """[N, N] bool: bodies linked through any chain of active joints (a body is linked to itself)."""
    body = jnp.arange(num_bodies)
    link = (joints.a_index[:, None] == body) & joints.active[:, None]
    other = (joints.b_index[:, None] == body) & joints.active[:, None]
    adjacency = (link[:, :, None] & other[:, None, :]).any(axis=0)
    reach = adjacency | adjacency.T | jnp.eye(num_bodies, dtype=bool)
    # Repeated squaring: after k rounds, chains of up to 2^k joints are closed.
    for _ in range(max(1, int(np.ceil(np.log2(max(num_bodies, 2)))))):
        reach = (reach[:, :, None] & reach[None, :, :]).any(axis=1)
    return reach


def arena_polygon_count(state: SimState) -> int:
    """Number of arena polygons, recovered from the pair count (arena-arena pairs are not enumerated)."""
    P, C = state.polygon_vertices.shape[0], state.circle_radius.shape[0]
    all_pairs = P * (P - 1) // 2 + P * C + C * (C - 1) // 2
    missing = all_pairs - state.pair_collides.shape[0]
    # missing = S (S - 1) / 2; S = 0 and S = 1 give the same pair tables, so 0 stands for both.
    return int(round((1 + np.sqrt(1 + 8 * missing)) / 2)) if missing else 0


def refresh_collision_filter(state: SimState) -> SimState:
    """Recompute which pairs may exchange contact impulses: bodies connected through joints never collide.

    Called by the joint helpers; call it after editing joints by hand. The step itself never recomputes it.
    """
    num_polygons = state.polygon_vertices.shape[0]
    num_circles = state.circle_radius.shape[0]
    sizes = SceneSizes(
        num_polygons=num_polygons,
        num_circles=num_circles,
        num_joints=state.joints.active.shape[0],
        num_thrusters=state.thrusters.active.shape[0],
        max_polygon_vertices=state.polygon_vertices.shape[1],
        num_static_polygons=arena_polygon_count(state),
    )
    tables = pair_tables(sizes)
    reach = connected_by_joints(state.joints, num_polygons + num_circles)
    return state.replace(pair_collides=~reach[tables.pair_a, tables.pair_b])
