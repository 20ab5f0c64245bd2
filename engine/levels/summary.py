"""A readable description of a level: its size class and what it uses of it, its task (and why it cannot be solved,
when it cannot: `engine.levels.checks`), shapes, joints, thrusters and what each action does."""

from __future__ import annotations

import numpy as np

from impulse.engine.levels.checks import unsolvable_reasons
from impulse.engine.levels.level import NUM_MOTOR_BINDINGS, NUM_THRUSTER_BINDINGS, ROLE_NAMES, Level
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes

_PRESETS = (("S", SIZE_S), ("M", SIZE_M), ("L", SIZE_L))
_ARENA_NAMES = ("floor", "left wall", "right wall", "ceiling")


def size_class(sizes: SceneSizes) -> str:
    """"S", "M" or "L" when the slot counts are one of Kinetix's sizes, else "custom"."""
    return next((name for name, preset in _PRESETS if sizes == preset), "custom")


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def describe_sizes(sizes: SceneSizes) -> str:
    """E.g. "S (5 polygons incl. 4 arena, 2 circles, 1 joint, 1 thruster)"."""
    return (f"{size_class(sizes)} ({_count(sizes.num_polygons, 'polygon')} incl. {sizes.num_static_polygons} "
            f"arena, {_count(sizes.num_circles, 'circle')}, {_count(sizes.num_joints, 'joint')}, "
            f"{_count(sizes.num_thrusters, 'thruster')})")


def _size_label(sizes: SceneSizes) -> str:
    """"S", "M" or "L", else the slot counts."""
    name = size_class(sizes)
    return name if name != "custom" else describe_sizes(sizes)


def describe_use(level: Level, sizes: SceneSizes) -> str:
    """What an (unbatched) level uses of its slots: its active shapes, joints and thrusters, e.g. "6 polygons incl.
    4 arena, 2 circles, 2 joints, 0 thrusters" (a Kinetix file holds every slot of its size, used or not)."""
    P, S = sizes.num_polygons, sizes.num_static_polygons
    active = np.asarray(level.state.bodies.active, bool)
    joints = int(np.asarray(level.state.joints.active, bool).sum())
    thrusters = int(np.asarray(level.state.thrusters.active, bool).sum())
    return (f"{_count(int(active[:P].sum()), 'polygon')} incl. {int(active[:S].sum())} arena, "
            f"{_count(int(active[P:].sum()), 'circle')}, {_count(joints, 'joint')}, {_count(thrusters, 'thruster')}")


def _xy(v) -> str:
    return f"({float(v[0]):.2f}, {float(v[1]):.2f})"


def _body_name(index: int, num_polygons: int, roles: np.ndarray) -> str:
    kind = "polygon" if index < num_polygons else "circle"
    role = ROLE_NAMES[roles[index]] if 0 <= roles[index] < len(ROLE_NAMES) else f"role {roles[index]}"
    return f"{role} {kind} #{index}"


def describe_level(
    level: Level,
    sizes: SceneSizes,
    *,
    file_sizes: SceneSizes | None = None,
    params: SimParams | None = None,
    frame_skip: int | None = None,
) -> str:
    """Several lines of text: sizes, task, every active shape, joint and thruster, and the action layout."""
    s = _host_arrays(level)
    b = s["bodies"]
    P = sizes.num_polygons
    roles = s["roles"]
    active = b["active"]
    lines = []
    size = _size_label(sizes)
    if file_sizes is not None and file_sizes != sizes:
        size = f"{_size_label(file_sizes)} in the file, loaded as {size}"
    lines.append(f"size: {size}; in use: {describe_use(level, sizes)}")
    if frame_skip is not None:
        lines.append(f"physics: {frame_skip} sub-steps per action"
                     + (f" of {float(params.dt):.4f} s" if params is not None else "")
                     + f", gravity {_xy(s['gravity'])}")

    present = {ROLE_NAMES[r] for r in roles[active] if 0 <= r < len(ROLE_NAMES)}
    task = "task: make a green shape touch a blue shape" + (
        " without any green shape touching a red one" if "red" in present else ""
    )
    reasons = unsolvable_reasons(level, sizes)
    if reasons:
        task += f" (it cannot be solved: {'; '.join(reasons)})"
    lines.append(task)

    lines.append("shapes:")
    for i in np.flatnonzero(active):
        role = ROLE_NAMES[roles[i]] if 0 <= roles[i] < len(ROLE_NAMES) else f"role {roles[i]}"
        fixed = b["inverse_mass"][i] == 0
        if i < P:
            n = int(s["n_vertices"][i])
            local = s["vertices"][i, :n]
            extent = local.max(axis=0) - local.min(axis=0)
            kind = "rectangle" if n == 4 and _is_rectangle(local) else f"{n}-gon"
            geometry = f"{kind} {extent[0]:.2f} x {extent[1]:.2f} m"
            if i < sizes.num_static_polygons and i < len(_ARENA_NAMES):
                geometry += f" ({_ARENA_NAMES[i]})"
        else:
            geometry = f"circle r {float(s['radius'][i - P]):.2f} m"
        lines.append(
            f"  #{i:<2} {role:<7} {geometry}, at {_xy(b['position'][i])}, rotation {float(b['rotation'][i]):.2f}, "
            f"{'fixed' if fixed else 'dynamic'}, friction {float(b['friction'][i]):.2f}, "
            f"collision mode {int(b['collision_mode'][i])}, density {float(s['densities'][i]):.2f}"
        )

    j = s["joints"]
    joint_slots = np.flatnonzero(j["active"])
    lines.append("joints:" if joint_slots.size else "joints: none")
    for k in joint_slots:
        a, c = int(j["a_index"][k]), int(j["b_index"][k])
        link = f"{_body_name(a, P, roles)} - {_body_name(c, P, roles)}"
        if j["is_fixed_joint"][k]:
            lines.append(f"  joint {k}: fixed (weld), {link}")
            continue
        text = f"  joint {k}: revolute, {link}"
        if j["motor_on"][k]:
            text += (f", motor speed x{float(j['motor_speed'][k]):.2f} power x{float(j['motor_power'][k]):.2f}, "
                     f"motor binding {int(s['motor_bindings'][k])}")
        else:
            text += ", no motor (free)"
        if j["motor_has_joint_limits"][k]:
            text += f", limits {float(j['min_rotation'][k]):.2f}..{float(j['max_rotation'][k]):.2f} rad"
        lines.append(text)

    t = s["thrusters"]
    thruster_slots = np.flatnonzero(t["active"])
    lines.append("thrusters:" if thruster_slots.size else "thrusters: none")
    for k in thruster_slots:
        body = int(t["body_index"][k])
        lines.append(
            f"  thruster {k}: on {_body_name(body, P, roles)}, offset {_xy(t['relative_position'][k])}, "
            f"direction {float(t['rotation'][k]):.2f} rad (body frame), power x{float(t['power'][k]):.2f}, "
            f"thruster binding {int(s['thruster_bindings'][k])}"
        )

    lines.append("controls (unified action: 4 motor values in [-1, 1], then 2 thruster values in [0, 1]):")
    motors = [k for k in joint_slots if j["motor_on"][k] and not j["is_fixed_joint"][k]]
    for binding in range(NUM_MOTOR_BINDINGS):
        driven = [k for k in motors if s["motor_bindings"][k] == binding]
        if driven:
            what = "; ".join(
                f"joint {k} (+1 spins {_body_name(int(j['b_index'][k]), P, roles)} counter-clockwise relative to "
                f"{_body_name(int(j['a_index'][k]), P, roles)})"
                for k in driven
            )
        else:
            what = "nothing"
        lines.append(f"  motor action {binding}: {what}")
    for binding in range(NUM_THRUSTER_BINDINGS):
        driven = [k for k in thruster_slots if s["thruster_bindings"][k] == binding]
        what = "; ".join(f"fires thruster {k} on {_body_name(int(t['body_index'][k]), P, roles)}" for k in driven)
        lines.append(f"  thruster action {binding}: {what or 'nothing'}")
    return "\n".join(lines)


def _is_rectangle(local: np.ndarray) -> bool:
    edges = np.roll(local, -1, axis=0) - local
    dots = np.einsum("ij,ij->i", edges, np.roll(edges, -1, axis=0))
    return bool(np.all(np.abs(dots) < 1e-4 * max(1.0, float(np.abs(edges).max()) ** 2)))


def _host_arrays(level: Level) -> dict:
    """The level's arrays as numpy, in a flat dict (one unbatched level)."""
    s = level.state
    return {
        "bodies": {k: np.asarray(v) for k, v in vars(s.bodies).items()},
        "joints": {k: np.asarray(v) for k, v in vars(s.joints).items()},
        "thrusters": {k: np.asarray(v) for k, v in vars(s.thrusters).items()},
        "vertices": np.asarray(s.polygon_vertices),
        "n_vertices": np.asarray(s.polygon_n_vertices),
        "radius": np.asarray(s.circle_radius),
        "gravity": np.asarray(s.gravity),
        "roles": np.asarray(level.roles),
        "densities": np.asarray(level.densities),
        "motor_bindings": np.asarray(level.motor_bindings),
        "thruster_bindings": np.asarray(level.thruster_bindings),
    }
