"""Level files: Kinetix JSON export and import (exact round trips both ways), padding into larger sizes, and the
errors a malformed or oversized file gives."""

from __future__ import annotations

import contextlib
import copy
import functools
import json
import os
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from impulse.engine.levels.kinetix_json import (
    MAX_LEVEL_FILE_BYTES,
    LevelFileError,
    level_file_problems,
    level_to_json_dict,
    load_kinetix_level,
    save_kinetix_level,
)
from impulse.engine.levels.level import Level, level_from_scene, with_content_id
from impulse.engine.physics.building import (
    add_circle,
    add_fixed_joint,
    add_polygon,
    add_rectangle,
    add_revolute_joint,
    add_thruster,
    empty_scene,
    refresh_collision_filter,
)
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.pairs import pair_tables
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SIZE_L, SIZE_M, SIZE_S, SceneSizes
from tests.support.bad_level_files import good_level_text, truncation_point, write_bad_inputs
from tests.support.paths import REPO

REPO_ROOT = REPO
LEVELS = REPO_ROOT / ".." / "shared" / "kinetix-levels"
PRESETS = (("s", SIZE_S), ("m", SIZE_M), ("l", SIZE_L))


def shared_level_files() -> list[Path]:
    if not LEVELS.is_dir():
        pytest.skip(f"Kinetix level files not found at {LEVELS.resolve()} (the shared folder beside the checkout)")
    files = sorted(LEVELS.rglob("*.json"))
    if not files:
        pytest.skip(f"no .json level files under {LEVELS.resolve()}")
    return files


def build_level(sizes: SceneSizes = SIZE_M) -> Level:
    """A valid level of `sizes` (see `_build_level`), built by one compiled call per size."""
    return jax.tree.map(np.asarray, _compiled_builder(sizes)())


@functools.cache
def _compiled_builder(sizes: SceneSizes):
    return jax.jit(functools.partial(_build_level, sizes))


def _build_level(sizes: SceneSizes) -> Level:
    """A valid level using every kind of thing a file stores: a green box with a thruster, a blue fixed circle,
    a neutral triangle hinged to the box by a motor with limits, a red circle welded to the triangle."""
    s = empty_scene(sizes)
    s, box = add_rectangle(s, (1.5, 2.0), 0.6, 0.4, density=1.5, friction=0.4)
    s, blue = add_circle(s, (4.0, 1.0), 0.3, fixed=True)
    if sizes.num_polygons - sizes.num_static_polygons >= 2:
        s, tri = add_polygon(s, (2.4, 2.0), [(-0.2, 0.2), (0.3, -0.1), (-0.2, -0.2)], rotation=0.3)
    else:  # S has one free polygon slot: hinge the box to the red circle instead
        tri = None
    s, red = add_circle(s, (2.9, 2.0), 0.15, density=2.0, collision_mode=2)
    hinged, offset = (tri, 0.45) if tri is not None else (red, 0.7)
    s, _ = add_revolute_joint(s, box, hinged, (offset, 0.0), (offset - 0.9, 0.0), motor_on=True, motor_speed=1.5,
                              motor_power=2.0, has_joint_limits=True, min_rotation=-0.5, max_rotation=0.7)
    if tri is not None and sizes.num_joints > 1:
        s, _ = add_fixed_joint(s, tri, red, (0.25, 0.0), (-0.25, 0.0))
    s, _ = add_thruster(s, box, (0.0, -0.1), rotation=np.pi / 2, power=0.8)
    roles = jnp.zeros(sizes.num_bodies, jnp.int32).at[jnp.stack([box, blue, red])].set(jnp.array([1, 2, 3]))
    densities = jnp.ones(sizes.num_bodies, jnp.float32).at[jnp.stack([box, red])].set(jnp.array([1.5, 2.0]))
    motor_bindings = np.zeros(sizes.num_joints, np.int32)
    motor_bindings[0] = 2
    thruster_bindings = np.zeros(sizes.num_thrusters, np.int32)
    thruster_bindings[0] = 1
    return level_from_scene(s, roles, densities, motor_bindings, thruster_bindings)


def fuzz_level(sizes: SceneSizes, seed: int) -> Level:
    """A level whose every array holds random bit patterns (any finite float32 incl. -0, subnormals and huge
    values; any int32; random bools), except where the loader insists: active joints and thrusters point at
    bodies, active shapes have roles 0..3 and active links bindings in range. Not a sensible scene."""
    rng = np.random.default_rng(seed)

    def floats(shape) -> np.ndarray:
        bits = rng.integers(0, 2**32, size=shape, dtype=np.uint64).astype(np.uint32).view(np.float32)
        out = np.where(np.isfinite(bits), bits, np.float32(1.5)).astype(np.float32)
        flat = out.reshape(-1)
        if flat.size >= 3:
            flat[:3] = [-0.0, np.float32(1e-45), np.float32(3.4e38)]
        return out

    def fuzz(leaf: np.ndarray) -> np.ndarray:
        leaf = np.asarray(leaf)
        if leaf.dtype == np.bool_:
            return rng.integers(0, 2, leaf.shape).astype(bool)
        if leaf.dtype.kind == "i":
            return rng.integers(-(2**31), 2**31, leaf.shape).astype(leaf.dtype)
        if leaf.dtype.kind == "u":
            return rng.integers(0, 2**32, leaf.shape).astype(leaf.dtype)
        return floats(leaf.shape)

    shapes = jax.eval_shape(lambda: level_from_scene(empty_scene(sizes)))
    level: Level = jax.tree.map(lambda leaf: fuzz(np.zeros(leaf.shape, leaf.dtype)), shapes)
    N = sizes.num_bodies
    joints = level.state.joints.replace(
        a_index=rng.integers(0, N, sizes.num_joints).astype(np.int32),
        b_index=rng.integers(0, N, sizes.num_joints).astype(np.int32),
    )
    thrusters = level.state.thrusters.replace(body_index=rng.integers(0, N, sizes.num_thrusters).astype(np.int32))
    active = np.asarray(level.state.bodies.active)
    roles = np.where(active, rng.integers(0, 4, N), np.asarray(level.roles)).astype(np.int32)
    motor = np.where(joints.active, rng.integers(0, 4, sizes.num_joints), level.motor_bindings).astype(np.int32)
    thrust = np.where(thrusters.active, rng.integers(0, 2, sizes.num_thrusters), level.thruster_bindings)
    state = level.state.replace(joints=joints, thrusters=thrusters)
    state = jax.tree.map(np.asarray, jax.jit(refresh_collision_filter)(state))
    return level.replace(state=state, roles=roles, motor_bindings=motor, thruster_bindings=thrust.astype(np.int32))


def assert_bitwise_equal(a, b) -> None:
    """Equal to the bit; a level's id is compared as the content hash the file's level carries."""
    if isinstance(b, Level):
        b = with_content_id(b)
    leaves_a, tree_a = jax.tree_util.tree_flatten_with_path(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten_with_path(b)
    assert [p for p, _ in leaves_a] == [p for p, _ in leaves_b]
    for (path, x), (_, y) in zip(leaves_a, leaves_b):
        x, y = np.asarray(x), np.asarray(y)
        name = jax.tree_util.keystr(path)
        assert x.dtype == y.dtype and x.shape == y.shape, (name, x.dtype, y.dtype, x.shape, y.shape)
        assert x.tobytes() == y.tobytes(), f"{name} differs:\n{x}\n{y}"


# ---------------------------------------------------------------------------------------------------------------
# Export -> import


@pytest.mark.parametrize("name, sizes", PRESETS)
def test_built_level_round_trip_is_exact(tmp_path: Path, name: str, sizes: SceneSizes) -> None:
    level = build_level(sizes)
    params = SimParams(dt=1.0 / 120.0, clip_position=12.5, base_friction=0.3)
    path = save_kinetix_level(tmp_path / f"{name}.json", level, sizes, params, frame_skip=3)
    loaded = load_kinetix_level(path)  # validates: a built level is a valid scene
    assert loaded.sizes == sizes and loaded.file_sizes == sizes
    assert loaded.params == params and loaded.frame_skip == 3
    assert_bitwise_equal(loaded.level, level)


@pytest.mark.parametrize("seed", range(3))
def test_fuzzed_level_round_trip_is_bitwise_exact(tmp_path: Path, seed: int) -> None:
    sizes = SceneSizes(num_polygons=7, num_circles=3, num_joints=2, num_thrusters=2)
    level = fuzz_level(sizes, seed)
    path = save_kinetix_level(tmp_path / "fuzz.json", level, sizes)
    loaded = load_kinetix_level(path, validate=False)
    assert_bitwise_equal(loaded.level, level)
    # Saving what was loaded writes the same file again.
    again = save_kinetix_level(tmp_path / "again.json", loaded.level, loaded.sizes, loaded.params, loaded.frame_skip,
                               loaded.options)
    assert again.read_text() == path.read_text()


def test_solver_options_of_a_file_round_trip_apart_from_its_sizes(tmp_path: Path) -> None:
    # A file's num_solver_iterations and do_warm_starting are solver options, not slot counts: they come back as
    # `options`, the sizes stay the preset, and saving with them writes them again.
    options = SolverOptions(iterations=4, warm_starting=False)
    path = save_kinetix_level(tmp_path / "solver.json", build_level(SIZE_S), SIZE_S, options=options)
    static = json.loads(path.read_text())["static_env_params"]
    assert (static["num_solver_iterations"], static["do_warm_starting"]) == (4, False)
    loaded = load_kinetix_level(path)
    assert loaded.options == options and loaded.sizes == SIZE_S == loaded.file_sizes


def test_contact_cache_goes_to_kinetix_manifolds_interleaved() -> None:
    sizes = SIZE_M
    level = build_level(sizes)
    tables = pair_tables(sizes)
    K = tables.num_contacts
    cache = level.state.contacts.replace(
        normal_impulse=np.arange(K, dtype=np.float32) + 0.5,
        tangent_impulse=-np.arange(K, dtype=np.float32),
        active=np.arange(K) % 3 == 0,
    )
    data = level_to_json_dict(level.replace(state=level.state.replace(contacts=cache)), sizes)
    rr = data["env_state"]["acc_rr_manifolds"]
    n_rr = tables.num_rr
    assert len(rr) == 2 * n_rr == 2 * (6 * 5 // 2 - 6)
    assert len(data["env_state"]["acc_cr_manifolds"]) == 6 * 3
    assert len(data["env_state"]["acc_cc_manifolds"]) == 3
    # Kinetix stores pair i's two points at entries 2i and 2i+1; the engine keeps all point-0 slots first.
    assert rr[2]["acc_impulse_normal"] == 1.5 and rr[3]["acc_impulse_normal"] == n_rr + 1.5
    assert data["env_state"]["acc_cr_manifolds"][0]["acc_impulse_tangent"] == -2.0 * n_rr
    assert rr[0]["active"] is True and rr[1]["active"] is (n_rr % 3 == 0)


def test_export_matches_kinetix_structure() -> None:
    """Key by key against a Kinetix file: same keys in the same order, same list lengths, same value types."""
    path = LEVELS / "s" / "h4_thrust_aim.json"
    if not path.is_file():
        pytest.skip(f"{path} not found (the shared Kinetix levels beside the checkout)")
    raw = json.loads(path.read_text())
    loaded = load_kinetix_level(path)
    ours = level_to_json_dict(loaded.level, loaded.sizes, loaded.params, loaded.frame_skip)

    def same_structure(a, b, where: str) -> None:
        assert type(a) is type(b), f"{where}: {type(a).__name__} vs {type(b).__name__}"
        if isinstance(a, dict):
            assert list(a) == list(b), f"{where}: keys {list(a)} vs {list(b)}"
            for key in a:
                same_structure(a[key], b[key], f"{where}.{key}")
        elif isinstance(a, list):
            assert len(a) == len(b), f"{where}: length {len(a)} vs {len(b)}"
            for i, (x, y) in enumerate(zip(a, b)):
                same_structure(x, y, f"{where}[{i}]")

    same_structure(ours, raw, "")
    assert ours["env_params"] == raw["env_params"]
    assert ours["static_env_params"] == raw["static_env_params"]
    assert ours["env_state"]["collision_matrix"] == raw["env_state"]["collision_matrix"]


# ---------------------------------------------------------------------------------------------------------------
# Shared Kinetix levels

# Leftovers Kinetix writes but its loader (and ours) never reads.
_UNREAD = {"polygon": ("radius",), "circle": ("n_vertices", "vertices")}


def _without_unread(data: dict) -> dict:
    data = copy.deepcopy(data)
    for key, fields in _UNREAD.items():
        for entry in data["env_state"][key]:
            for field in fields:
                entry.pop(field)
    return data


def test_shared_levels_import_export_round_trip(tmp_path: Path) -> None:
    """export(import(file)) reproduces every field the loader reads, and import(export(level)) is exact."""
    for path in shared_level_files():
        raw = json.loads(path.read_text())
        loaded = load_kinetix_level(path)
        exported = level_to_json_dict(loaded.level, loaded.sizes, loaded.params, loaded.frame_skip)
        assert _without_unread(exported) == _without_unread(raw), path.name
        out = save_kinetix_level(tmp_path / path.name, loaded.level, loaded.sizes, loaded.params, loaded.frame_skip,
                                 loaded.options)
        assert_bitwise_equal(load_kinetix_level(out).level, loaded.level)


def test_shared_levels_load_into_every_larger_size() -> None:
    for path in shared_level_files():
        native = load_kinetix_level(path)
        fs = native.sizes
        P, C = fs.num_polygons, fs.num_circles
        fitting = [sizes for _, sizes in PRESETS if fs.fits_in(sizes)]
        assert fitting and fitting[0].num_polygons == P, f"{path.name} is not in a Kinetix size"
        for sizes in fitting[1:]:
            padded = load_kinetix_level(path, sizes)
            assert padded.sizes == sizes and padded.file_sizes == fs
            # Old body index -> new one: circles move up by the polygon slots added.
            moved = np.concatenate([np.arange(P), np.arange(C) + sizes.num_polygons])
            nb, pb = native.state.bodies, padded.state.bodies
            for field in ("position", "rotation", "active", "inverse_mass", "collision_mode"):
                assert np.array_equal(np.asarray(getattr(pb, field))[moved], np.asarray(getattr(nb, field)))
            assert not np.asarray(pb.active)[np.setdiff1d(np.arange(sizes.num_bodies), moved)].any()
            level_n, level_p = native.level, padded.level
            assert np.array_equal(np.asarray(level_p.roles)[moved], np.asarray(level_n.roles))
            assert np.array_equal(np.asarray(padded.state.circle_radius)[:C], np.asarray(native.state.circle_radius))
            # Joints and thrusters still hold the same bodies (compare the bodies' positions and the anchors).
            nj, pj = native.state.joints, padded.state.joints
            for side in ("a_index", "b_index"):
                old = np.asarray(getattr(nj, side))
                new = np.asarray(getattr(pj, side))[: fs.num_joints]
                live = np.asarray(nj.active) & (old >= 0) & (old < P + C)
                assert np.array_equal(new[live], moved[old[live]]), (path.name, side)
            old_t = np.asarray(native.state.thrusters.body_index)
            new_t = np.asarray(padded.state.thrusters.body_index)[: fs.num_thrusters]
            live_t = np.asarray(native.state.thrusters.active)
            assert np.array_equal(new_t[live_t], moved[old_t[live_t]]), path.name
            assert np.array_equal(
                np.asarray(pb.position)[new_t[live_t]], np.asarray(nb.position)[old_t[live_t]]
            ), path.name
            assert not np.asarray(pj.active)[fs.num_joints :].any()
        for _, sizes in PRESETS:
            if not fs.fits_in(sizes):
                with pytest.raises(LevelFileError, match="too large for the size"):
                    load_kinetix_level(path, sizes)


def test_a_padded_level_compacts_back_into_its_own_size(tmp_path: Path) -> None:
    """`compact` drops the slots a file does not use: every shared S level padded into L (saved as an L file)
    loads back into S as the same scene: every used shape, joint and thruster in the same slot with the same
    values, the unused slots inactive (Kinetix's files keep leftover values in those, which the cut drops).
    Without `compact` the L file is refused, and a level that uses more than the smaller size allows is refused
    naming what it uses."""

    def used(loaded) -> dict[str, np.ndarray]:
        host = jax.tree.map(np.asarray, loaded.level)
        state, P = host.state, loaded.sizes.num_polygons
        body_on, joint_on, thruster_on = state.bodies.active, state.joints.active, state.thrusters.active
        out = {f"bodies.{name}": value[body_on] for name, value in vars(state.bodies).items()}
        out |= {f"joints.{name}": value[joint_on] for name, value in vars(state.joints).items()}
        out |= {f"thrusters.{name}": value[thruster_on] for name, value in vars(state.thrusters).items()}
        out |= {"active": body_on, "joints_on": joint_on, "thrusters_on": thruster_on,
                "roles": host.roles[body_on], "densities": host.densities[body_on],
                "vertices": state.polygon_vertices[body_on[:P]], "n_vertices": state.polygon_n_vertices[body_on[:P]],
                "radius": state.circle_radius[body_on[P:]], "motor_bindings": host.motor_bindings[joint_on],
                "thruster_bindings": host.thruster_bindings[thruster_on], "gravity": state.gravity}
        return out

    checked = 0
    for path in shared_level_files():
        if path.parent.name != "s":
            continue
        native = load_kinetix_level(path)
        padded = load_kinetix_level(path, SIZE_L)
        as_l = save_kinetix_level(tmp_path / path.name, padded.level, SIZE_L, padded.params, padded.frame_skip,
                                  padded.options)
        with pytest.raises(LevelFileError, match="too large for the size: the file has"):
            load_kinetix_level(as_l, SIZE_S)
        back = load_kinetix_level(as_l, SIZE_S, compact=True)
        assert back.sizes == SIZE_S and back.file_sizes == SIZE_L
        assert (back.params, back.frame_skip, back.options) == (native.params, native.frame_skip, native.options)
        expected, got = used(native), used(back)
        for name, value in expected.items():
            assert np.array_equal(got[name], value), (path.name, name)
        checked += 1
    assert checked >= 10
    for path in shared_level_files():
        if path.parent.name == "m":
            with pytest.raises(LevelFileError, match="too large for the size: the level uses"):
                load_kinetix_level(path, SIZE_S, compact=True)
            break


def test_padded_level_keeps_its_joints_in_place() -> None:
    """Each joint's two world anchors are as far apart in the padded scene as in the file's own size (the
    indices still name the same bodies); Kinetix's files hold a few joints that start slightly apart."""

    def anchor_gaps(state) -> np.ndarray:
        b, j = jax.tree.map(np.asarray, state.bodies), jax.tree.map(np.asarray, state.joints)

        def anchor(index, relative):
            angle = b.rotation[index]
            c, si = np.cos(angle), np.sin(angle)
            turned = np.stack([c * relative[:, 0] - si * relative[:, 1], si * relative[:, 0] + c * relative[:, 1]], -1)
            return b.position[index] + turned

        gap = anchor(j.a_index, j.a_relative_pos) - anchor(j.b_index, j.b_relative_pos)
        return gap[j.active]

    checked = 0
    for path in shared_level_files():
        if path.parent.name != "m":
            continue
        native, padded = load_kinetix_level(path), load_kinetix_level(path, SIZE_L)
        assert np.array_equal(anchor_gaps(native.state), anchor_gaps(padded.state)), path.name
        checked += len(anchor_gaps(native.state))
    assert checked > 0


# ---------------------------------------------------------------------------------------------------------------
# Bad files


def _valid_dict() -> dict:
    return level_to_json_dict(build_level(SIZE_M), SIZE_M)


def _set(*keys_and_value):
    *keys, value = keys_and_value

    def edit(data: dict) -> None:
        target = data
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value

    return edit


def _delete(*keys):
    def edit(data: dict) -> None:
        target = data
        for key in keys[:-1]:
            target = target[key]
        del target[keys[-1]]

    return edit


BAD_FILES = {
    "missing field": (_delete("env_state", "polygon", 4, "position"), ["polygon[4].position missing"]),
    "missing list": (_delete("env_state", "joint"), ["env_state.joint missing"]),
    "wrong vector shape": (
        _set("env_state", "polygon", 4, "position", {"0": 1.0, "1": 2.0, "2": 3.0}),
        ["polygon[4].position", "wrong shape"],
    ),
    "wrong vertex shape": (
        _set("env_state", "polygon", 5, "vertices", {"0": {"0": 1.0, "1": 2.0}}),
        ["polygon[5].vertices", "wrong shape"],
    ),
    "gapped array keys": (_set("env_state", "gravity", {"0": 0.0, "2": -9.8}), ["env_state.gravity", "array"]),
    "text instead of number": (_set("env_state", "circle", 0, "radius", "0.3"), ["circle[0].radius", "expected"]),
    "NaN": (_set("env_state", "circle", 1, "radius", float("nan")), ["circle[1].radius", "NaN"]),
    "infinity": (_set("env_state", "joint", 0, "motor_speed", float("inf")), ["joint[0].motor_speed", "NaN or inf"]),
    "float too large": (_set("env_state", "polygon", 4, "rotation", 1e300), ["polygon[4].rotation", "float32"]),
    "not an integer": (
        _set("env_state", "polygon", 4, "collision_mode", 1.5), ["polygon[4].collision_mode", "integer"]
    ),
    "bad role": (_set("env_state", "polygon", 4, "role", 7), ["polygon[4].role", "7 is not a role"]),
    "negative role": (_set("env_state", "circle", 0, "role", -1), ["circle[0].role", "not a role"]),
    "bad motor binding": (_set("env_state", "joint", 0, "motor_binding", 4), ["joint[0].motor_binding", "0..3"]),
    "bad thruster binding": (
        _set("env_state", "thruster", 0, "thruster_binding", 2), ["thruster[0].thruster_binding", "0..1"]
    ),
    "joint index out of range": (_set("env_state", "joint", 0, "b_index", 9), ["joint[0].b_index", "out of range"]),
    "thruster index out of range": (
        _set("env_state", "thruster", 0, "object_index", -1), ["thruster[0].object_index", "out of range"]
    ),
    "bool field": (_set("env_state", "joint", 1, "active", 3), ["joint[1].active", "true or false"]),
    "slot not an object": (_set("env_state", "circle", 2, [1, 2]), ["circle[2]", "expected an object"]),
    "static count disagrees": (
        _set("static_env_params", "num_polygons", 5), ["static_env_params.num_polygons", "6 slots"]
    ),
    "bad frame skip": (_set("static_env_params", "frame_skip", 0), ["static_env_params.frame_skip"]),
    "bad env param": (_set("env_params", "dt", "fast"), ["env_params.dt", "finite number"]),
    "manifold count": (_delete("env_state", "acc_cc_manifolds", 0), ["acc_cc_manifolds", "expected 3"]),
    "no env_state": (_delete("env_state"), ["not a level file", "env_state"]),
    "counter-clockwise polygon": (
        _set("env_state", "polygon", 4, "vertices", {
            str(i): {"0": x, "1": y} for i, (x, y) in enumerate([(-0.3, -0.2), (0.3, -0.2), (0.3, 0.2), (-0.3, 0.2)])
        }),
        ["invalid scene", "polygon 4", "counter-clockwise"],
    ),
    "joint to an inactive body": (_set("env_state", "circle", 1, "active", False), ["invalid scene", "joint 1"]),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_file_error_names_file_field_and_problem(tmp_path: Path, case: str) -> None:
    edit, expected = BAD_FILES[case]
    data = _valid_dict()
    edit(data)
    path = tmp_path / "bad_level.json"
    path.write_text(json.dumps(data))
    with pytest.raises(LevelFileError) as info:
        load_kinetix_level(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    for part in expected:
        assert part in message, f"{part!r} not in {message!r}"
    assert level_file_problems(path) == info.value.problems


def test_valid_dict_is_valid(tmp_path: Path) -> None:
    path = tmp_path / "good.json"
    path.write_text(json.dumps(_valid_dict()))
    assert level_file_problems(path) == []
    load_kinetix_level(path)


def test_every_problem_is_reported_at_once(tmp_path: Path) -> None:
    data = _valid_dict()
    del data["env_state"]["polygon"][4]["position"]
    data["env_state"]["circle"][0]["role"] = 9
    data["env_state"]["joint"][0]["motor_binding"] = -2
    path = tmp_path / "many.json"
    path.write_text(json.dumps(data))
    with pytest.raises(LevelFileError) as info:
        load_kinetix_level(path)
    assert len(info.value.problems) == 3
    assert "3 problems" in str(info.value)


def test_not_json_and_unreadable(tmp_path: Path) -> None:
    path = tmp_path / "broken.json"
    path.write_text('{"env_state": {"polygon": [')
    with pytest.raises(LevelFileError, match=r"broken\.json: not valid JSON"):
        load_kinetix_level(path)
    path.write_text("[1, 2, 3]")
    with pytest.raises(LevelFileError, match="top level must be an object"):
        load_kinetix_level(path)
    with pytest.raises(LevelFileError, match=r"missing\.json: cannot read"):
        load_kinetix_level(tmp_path / "missing.json")


BAD_INPUTS = ("latin-1 text", "random bytes", "PNG image", "empty file", "blank file", "truncated JSON", "UTF-16 text",
              "folder")


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_file_that_is_not_a_level_file_gives_one_line_naming_it(tmp_path: Path, case: str) -> None:
    path, expected = write_bad_inputs(tmp_path)[case]
    with pytest.raises(LevelFileError) as info:
        load_kinetix_level(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    for part in expected:
        assert part in message, f"{part!r} not in {message!r}"
    assert level_file_problems(path) == info.value.problems  # `impulse levels validate` gets the same problem


def test_truncated_file_error_is_where_json_stops(tmp_path: Path) -> None:
    text = good_level_text()
    cut, line, column = truncation_point(text)
    assert line > 1  # the position is a line and column in a multi-line file, not only an offset
    path = tmp_path / "cut.json"
    path.write_text(text[:cut])
    with pytest.raises(LevelFileError, match=rf"cut\.json: not valid JSON: Expecting value: line {line} column "
                       rf"{column} \(char {cut}\); the text ends there: is the file cut short\?$"):
        load_kinetix_level(path)
    path.write_text(text + " }")  # broken, but not at the end: no hint about truncation
    with pytest.raises(LevelFileError, match="Extra data") as info:
        load_kinetix_level(path)
    assert "cut short" not in str(info.value)


def test_byte_order_mark_is_allowed_and_odd_json_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "bom.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(_valid_dict()).encode())
    assert level_file_problems(path) == []
    path.write_text("[" * 100_000)
    with pytest.raises(LevelFileError, match=r"bom\.json: not valid JSON: nested too deeply"):
        load_kinetix_level(path)
    path.write_text('{"env_state": ' + "7" * 5000 + "}")  # more digits than Python converts to an integer
    with pytest.raises(LevelFileError, match=r"bom\.json: not valid JSON: Exceeds the limit"):
        load_kinetix_level(path)


def test_pipe_device_and_oversized_files_are_refused_without_reading(tmp_path: Path) -> None:
    if hasattr(os, "mkfifo"):
        fifo = tmp_path / "pipe.json"
        os.mkfifo(fifo)  # reading it would block until a writer comes: the loader must not wait for one

        def unblock() -> None:  # should the loader wait after all, a writer comes and goes: the test fails, not hangs
            with contextlib.suppress(OSError):
                os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))

        timer = threading.Timer(10.0, unblock)
        timer.start()
        try:
            with pytest.raises(LevelFileError, match=r"pipe\.json: not a regular file"):
                load_kinetix_level(fifo)
        finally:
            timer.cancel()
    if Path("/dev/zero").exists():  # endless: reading it would fill memory
        with pytest.raises(LevelFileError, match="/dev/zero: not a regular file"):
            load_kinetix_level("/dev/zero")
    huge = tmp_path / "huge.json"
    with huge.open("wb") as file:
        file.truncate(MAX_LEVEL_FILE_BYTES + 1)  # sparse: no disk space used
    with pytest.raises(LevelFileError, match=r"huge\.json: too large for a level file"):
        load_kinetix_level(huge)


def test_file_without_read_permission(tmp_path: Path) -> None:
    locked = tmp_path / "locked.json"
    locked.write_text(json.dumps(_valid_dict()))
    locked.chmod(0)
    try:
        if os.access(locked, os.R_OK):  # root reads anything
            pytest.skip("running as root: a file without read permission is still readable")
        with pytest.raises(LevelFileError, match=r"locked\.json: cannot read the file: Permission denied"):
            load_kinetix_level(locked)
    finally:
        locked.chmod(0o644)


def test_too_many_shapes_for_the_size(tmp_path: Path) -> None:
    path = save_kinetix_level(tmp_path / "m_level.json", build_level(SIZE_M), SIZE_M)
    with pytest.raises(LevelFileError) as info:
        load_kinetix_level(path, SIZE_S)
    message = str(info.value)
    assert "m_level.json" in message and "too large for the size" in message
    assert "6 polygons (the size allows 5)" in message and "2 joints (the size allows 1)" in message


def test_validate_flag_lets_tools_load_an_invalid_scene(tmp_path: Path) -> None:
    edit, _ = BAD_FILES["counter-clockwise polygon"]
    data = _valid_dict()
    edit(data)
    path = tmp_path / "ccw.json"
    path.write_text(json.dumps(data))
    loaded = load_kinetix_level(path, validate=False)
    assert np.asarray(loaded.state.bodies.active)[4]
    problems = level_file_problems(path)
    assert len(problems) == 1 and "counter-clockwise" in problems[0]


def test_save_rejects_mismatched_sizes(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not match the sizes"):
        save_kinetix_level(tmp_path / "x.json", build_level(SIZE_M), SIZE_S)
