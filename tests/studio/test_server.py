"""Impulse Studio's server (`studio.app`) through Starlette's TestClient, no browser: the gallery's sets, counts and
thumbnails; a level's JSON round trip (GET, save, GET again gives the same level, for our hand-made files and
Kinetix's); the editor's operations and the size limit; bad input answered with a 4xx and a message naming the
problem while the server goes on; the play socket (a motor moves the car, a bad message is an error and the
socket stays usable); the access token and the same-origin check; `impulse studio`'s refusal to listen on the
network without a token; the warnings of a level that cannot be solved; the Run page's metrics routes; strict JSON
on the play socket; and the progress messages of a slow agent load. The client names the studio's host as a
browser would (127.0.0.1): the studio refuses any other (tests/studio/test_security.py tests that, and the rest of
the guard, over real HTTP)."""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from starlette.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from impulse.deploy.cli import main
from impulse.engine.levels import handmade
from impulse.engine.levels.handmade.files import level_differences
from impulse.engine.levels.kinetix_json import level_file_problems, load_kinetix_level
from impulse.engine.levels.sets import LevelSetError, kinetix_levels_root
from impulse.engine.physics.sizes import SIZE_S
from impulse.studio.app import make_app
from impulse.studio.level_io import load_document
from tests.support.paths import REPO

CAR = "s_easy_car_right"  # a motorised green wheel (motor binding 0) that drives right into a blue ball
THRUST = "s_easy_thrust_right"  # one polygon and one circle: an S level with a free circle slot
MOTOR_RIGHT = [1, 0, 0, 0, 0, 0]
NOOP = [0, 0, 0, 0, 0, 0]


@pytest.fixture(scope="module")
def levels_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("studio-levels")


PLAY = "ws://127.0.0.1/ws/play"
"""The play socket's address for the TestClient (whose own default host, testserver, the studio refuses)."""


def studio_client(app) -> TestClient:
    """A TestClient for a studio app, sending `Host: 127.0.0.1` (its default name, testserver, is refused)."""
    return TestClient(app, base_url="http://127.0.0.1")


@pytest.fixture(scope="module")
def client(levels_dir: Path) -> TestClient:
    with studio_client(make_app(levels_dir)) as client:
        yield client


def level_json(client: TestClient, set_id: str, name: str) -> dict:
    response = client.get("/api/level", params={"set": set_id, "name": name})
    assert response.status_code == 200, response.text
    return response.json()


def edit(client: TestClient, level: dict, ops: list[dict], size: str | None = None):
    return client.post("/api/edit", json={"level": level, "ops": ops, **({"size": size} if size else {})})


def green_circle_x(frame: dict) -> float:
    [green] = [c for c in frame["scene"]["circles"] if c["role"] == "green"]
    return green["centre"][0]


def test_gallery_lists_the_handmade_levels_with_their_counts_and_thumbnails(client: TestClient) -> None:
    sets = {s["id"]: s for s in client.get("/api/sets").json()["sets"]}
    assert {"handmade", "kinetix:s", "kinetix:m", "kinetix:l", "saved"} <= set(sets)
    levels = {entry["name"]: entry for entry in client.get("/api/levels", params={"set": "handmade"}).json()["levels"]}
    assert set(levels) == set(handmade.names())
    car = levels[CAR]
    assert (car["size"], car["polygons"], car["circles"], car["joints"], car["thrusters"]) == ("S", 1, 2, 1, 0)
    assert levels[THRUST]["thrusters"] == 1 and levels["l_claw"]["size"] == "L"
    png = client.get(car["thumbnail"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    image = np.asarray(Image.open(io.BytesIO(png.content)).convert("RGB"))
    assert image.shape == (160, 160, 3)
    assert ((image[..., 1] > 150) & (image[..., 0] < 60)).any(), "the green wheel is drawn"
    assert client.get("/api/levels", params={"set": "nope"}).status_code == 404


def kinetix_level() -> tuple[str, str]:
    try:
        kinetix_levels_root()
    except LevelSetError as err:
        pytest.skip(f"Kinetix's level files are not here ({err})")
    return "kinetix:s", "h0_weak_thrust"


@pytest.mark.parametrize("which", ["handmade", "kinetix"])
def test_a_level_survives_get_save_get_unchanged(client: TestClient, levels_dir: Path, which: str) -> None:
    set_id, name = ("handmade", CAR) if which == "handmade" else kinetix_level()
    original = level_json(client, set_id, name)
    saved = client.post("/api/save", json={"name": f"copy_{which}", "level": original})
    assert saved.status_code == 200, saved.text
    assert saved.json()["saved"] == {"set": "saved", "name": f"copy_{which}"}
    again = level_json(client, "saved", f"copy_{which}")
    assert again == original
    path = levels_dir / f"copy_{which}.json"
    origin = handmade.level_file(name) if which == "handmade" else kinetix_levels_root() / "s" / f"{name}.json"
    assert level_differences(load_kinetix_level(path).level, load_kinetix_level(origin).level) == []
    assert level_file_problems(path) == []


def test_bad_input_is_a_4xx_naming_the_problem_and_the_server_goes_on(client: TestClient) -> None:
    not_json = client.post("/api/save", content=b"{\"name\": ", headers={"content-type": "application/json"})
    assert not_json.status_code == 400 and "not valid JSON" in not_json.json()["error"]

    level = level_json(client, "handmade", CAR)
    del level["env_state"]["circle"][0]["position"]
    missing = client.post("/api/validate", json={"level": level})
    assert missing.status_code == 422 and "circle[0].position missing" in missing.json()["problems"]

    big = level_json(client, "handmade", "m_car_bump")
    too_big = client.post("/api/save", json={"name": "big", "level": big, "size": "s"})
    assert too_big.status_code == 422
    assert any("too large for the size" in p for p in too_big.json()["problems"]), too_big.json()
    assert client.post("/api/validate", json={"level": big, "size": "m"}).json()["valid"] is True

    assert client.post("/api/save", json={"name": "../escape", "level": big}).status_code == 422
    assert client.post("/api/save", json={"name": "x", "level": [1, 2]}).status_code == 422
    assert client.post("/api/save", content=b"{}", headers={"content-type": "text/plain"}).status_code == 415
    assert client.get("/api/level", params={"set": "handmade", "name": "../../etc/passwd"}).status_code == 404
    no_run = client.post("/api/inject", json={"level": big})  # started without --run: nowhere to send a level
    assert no_run.status_code == 409 and "--run" in no_run.json()["error"]
    assert client.get("/api/agents").json()["inject_run"] is None
    assert client.get("/api/sets").status_code == 200


def test_editing_adds_moves_re_roles_fixes_and_deletes_within_the_size(client: TestClient) -> None:
    level = level_json(client, "handmade", THRUST)
    added = edit(client, level, [{"op": "add_circle", "x": 2.5, "y": 3.0, "radius": 0.2, "role": "red"}])
    assert added.status_code == 200, added.text
    state = added.json()
    assert state["counts"]["circles"] == 2 and state["problems"] == []
    [new] = [c for c in state["scene"]["circles"] if c["centre"] == [2.5, 3.0]]
    assert new["role"] == "red" and not new["fixed"] and new["radius"] == 0.2

    full = edit(client, state["level"], [{"op": "add_circle", "x": 1.0, "y": 3.0}])
    assert full.status_code == 422 and "no free circle slot" in full.json()["error"]

    changed = edit(client, state["level"], [
        {"op": "set_fixed", "body": new["body"], "fixed": True},
        {"op": "set_role", "body": new["body"], "role": "blue"},
        {"op": "move", "body": new["body"], "dx": 0.5, "dy": -0.5},
    ]).json()
    [moved] = [c for c in changed["scene"]["circles"] if c["body"] == new["body"]]
    assert moved["centre"] == [3.0, 2.5] and moved["role"] == "blue" and moved["fixed"]
    freed = edit(client, changed["level"], [{"op": "set_fixed", "body": new["body"], "fixed": False}]).json()
    assert not [c for c in freed["scene"]["circles"] if c["body"] == new["body"]][0]["fixed"]

    gone = edit(client, freed["level"], [{"op": "delete", "body": new["body"]}]).json()
    assert gone["counts"]["circles"] == 1
    assert edit(client, gone["level"], [{"op": "delete", "body": 0}]).status_code == 422  # the floor stays
    assert edit(client, gone["level"], [{"op": "explode"}]).status_code == 422
    saved = client.post("/api/save", json={"name": "edited", "level": freed["level"]})
    assert saved.status_code == 200, saved.text


def test_editing_joints_thrusters_materials_sizes_and_triangles(client: TestClient, levels_dir: Path) -> None:
    """A wheel pinned to the world by a motorised joint, a triangle in the freed polygon slot with a thruster, a
    material change and a resize: each shows in the reply, is refused past the size's limits, survives saving as
    Kinetix JSON, and the motor turns the wheel in play."""
    level = level_json(client, "handmade", THRUST)  # S: the arena (bodies 0-3), a box (4) and a circle (5)

    def edited(state: dict, ops: list[dict]) -> dict:
        reply = edit(client, state["level"] if "scene" in state else state, ops)
        assert reply.status_code == 200, reply.text
        return reply.json()

    state = edited(level, [{"op": "add_circle", "x": 2.5, "y": 2.5, "radius": 0.2}])
    wheel = state["scene"]["circles"][-1]["body"]
    state = edited(state, [{"op": "add_joint", "a": 0, "b": wheel, "x": 2.5, "y": 2.5, "motor": True, "speed": 2,
                            "power": 2, "limits": [-1, 1], "binding": 0}])
    [joint] = state["actuators"]["joints"]
    assert joint == {"joint": 0, "a": 0, "b": wheel, "weld": False, "motor": True, "speed": 2.0, "power": 2.0,
                     "limits": [-1.0, 1.0], "binding": 0}
    assert state["scene"]["joints"][0]["position"] == [2.5, 2.5] and state["problems"] == []
    state = edited(state, [{"op": "set_joint", "joint": 0, "limits": None, "binding": 1},
                           {"op": "set_joint", "joint": 0, "binding": 0}])
    assert state["actuators"]["joints"][0]["limits"] is None and state["actuators"]["joints"][0]["motor"]
    full = edit(client, state["level"], [{"op": "add_joint", "a": 4, "b": 5, "x": 1.2, "y": 0.6}])
    assert full.status_code == 422 and "at most 1 joints" in full.json()["error"]
    same = edit(client, state["level"], [{"op": "add_joint", "a": wheel, "b": wheel, "x": 2.5, "y": 2.5}])
    assert same.status_code == 422 and "two different shapes" in same.json()["error"]

    no_slot = edit(client, state["level"], [{"op": "add_polygon", "x": 1.0, "y": 2.0, "sides": 3}])
    assert no_slot.status_code == 422 and "no free polygon slot" in no_slot.json()["error"]
    state = edited(state, [{"op": "delete", "body": 4},  # the box goes with its thruster
                           {"op": "add_polygon", "x": 1.0, "y": 2.0, "width": 0.6, "height": 0.3, "sides": 3},
                           {"op": "add_thruster", "body": 4, "angle": 0.0, "power": 2, "binding": 1},
                           {"op": "set_material", "body": wheel, "density": 3, "friction": 0.2,
                            "restitution": 0.5},
                           {"op": "resize", "body": wheel, "scale": 1.5}])
    [triangle] = [p for p in state["scene"]["polygons"] if p["body"] == 4]
    assert len(triangle["points"]) == 3
    assert state["actuators"]["thrusters"] == [{"thruster": 0, "body": 4, "power": 2.0, "angle": 0.0, "binding": 1}]
    state = edited(state, [{"op": "set_thruster", "thruster": 0, "power": 2.5, "angle": math.pi / 2}])
    assert state["actuators"]["thrusters"] == [{"thruster": 0, "body": 4, "power": 2.5,
                                                "angle": round(math.pi / 2, 4), "binding": 1}]
    assert [c["radius"] for c in state["scene"]["circles"] if c["body"] == wheel] == [0.3]
    too_big = edit(client, state["level"], [{"op": "resize", "body": wheel, "scale": 10}])
    assert too_big.status_code == 422 and "across" in too_big.json()["error"]

    # Into size M: the same level in more slots, with room for another circle.
    bigger = edit(client, state["level"], [], size="m")
    assert bigger.status_code == 200 and bigger.json()["size"] == "M", bigger.text
    assert bigger.json()["counts"] == state["counts"]

    def settings(actuators: dict) -> list:  # body indices move with the size's slot layout; settings do not
        return [{k: v for k, v in item.items() if k not in ("a", "b", "body")}
                for item in actuators["joints"] + actuators["thrusters"]]

    assert settings(bigger.json()["actuators"]) == settings(state["actuators"])
    added = edited(bigger.json(), [{"op": "add_circle", "x": 4.0, "y": 4.0, "radius": 0.2}])
    assert added["counts"]["circles"] == state["counts"]["circles"] + 1
    # Back down: the unused slots are dropped, so the level returns to S as it was; one that uses more than S
    # holds is refused, naming what it uses.
    smaller = edit(client, bigger.json()["level"], [], size="s")
    assert smaller.status_code == 200 and smaller.json()["size"] == "S", smaller.text
    assert smaller.json()["counts"] == state["counts"] and smaller.json()["problems"] == []
    assert smaller.json()["actuators"] == state["actuators"]
    assert [c["radius"] for c in smaller.json()["scene"]["circles"] if c["body"] == wheel] == [0.3]
    assert added["counts"]["circles"] > SIZE_S.num_circles
    refused = edit(client, added["level"], [], size="s")
    assert refused.status_code == 422 and "too large for the size: the level uses" in refused.text, refused.text

    saved = client.post("/api/save", json={"name": "jointed", "level": state["level"]})
    assert saved.status_code == 200, saved.text
    assert level_file_problems(levels_dir / "jointed.json") == []
    back = load_kinetix_level(levels_dir / "jointed.json").level
    bodies, joints, thrusters = back.state.bodies, back.state.joints, back.state.thrusters
    assert bool(joints.motor_on[0]) and float(joints.motor_speed[0]) == 2.0 and int(joints.b_index[0]) == wheel
    assert int(back.state.polygon_n_vertices[4]) == 3 and float(thrusters.power[0]) == 2.5
    assert int(back.thruster_bindings[0]) == 1
    assert float(bodies.friction[wheel]) == pytest.approx(0.2) and float(bodies.restitution[wheel]) == 0.5
    # Three times the density, 1.5 times the radius: 6.75 times the mass of the disc added at density 1.
    original = load_kinetix_level(handmade.level_file(THRUST)).level.state.bodies
    added = edited(level, [{"op": "add_circle", "x": 2.5, "y": 2.5, "radius": 0.2}])
    first = load_document(added["level"]).level.state.bodies
    assert float(first.inverse_mass[wheel] / bodies.inverse_mass[wheel]) == pytest.approx(6.75, rel=1e-4)
    assert not bool(original.active[wheel])

    with client.websocket_connect(PLAY) as socket:  # the motor turns the pinned wheel; the pin holds it
        socket.send_json({"type": "load", "level": state["level"]})
        start = socket.receive_json()["scene"]["circles"]
        for _ in range(10):
            socket.send_json({"type": "step", "action": MOTOR_RIGHT})
            frame = socket.receive_json()
    [before] = [c for c in start if c["body"] == wheel]
    [after] = [c for c in frame["scene"]["circles"] if c["body"] == wheel]
    assert np.hypot(*np.subtract(after["centre"], before["centre"])) < 0.01
    assert np.hypot(*np.subtract(after["mark"], before["mark"])) > 0.05, "the motor turned the wheel"


def test_moving_a_car_moves_its_wheels_along(client: TestClient) -> None:
    state = edit(client, level_json(client, "handmade", CAR), []).json()
    [chassis] = [p for p in state["scene"]["polygons"] if p["body"] >= 4]
    before = {c["body"]: c["centre"] for c in state["scene"]["circles"]}
    moved = edit(client, state["level"], [{"op": "move", "body": chassis["body"], "dx": 0.5, "dy": 0.0}]).json()
    linked = [c for c in moved["scene"]["circles"] if c["centre"] != before[c["body"]]]
    assert linked, "a wheel joined to the chassis moves with it"
    for circle in linked:
        assert circle["centre"] == pytest.approx([before[circle["body"]][0] + 0.5, before[circle["body"]][1]])
    assert moved["problems"] == []


def test_play_socket_steps_the_level_and_a_motor_moves_the_car(client: TestClient) -> None:
    with client.websocket_connect(PLAY) as socket:
        socket.send_json({"type": "step", "action": NOOP, "seq": 1})
        early = socket.receive_json()
        assert early["type"] == "error" and "no level loaded" in early["message"] and early["seq"] == 1

        socket.send_json({"type": "load", "set": "handmade", "name": CAR})
        loaded = socket.receive_json()
        assert loaded["type"] == "state" and loaded["t"] == 0 and loaded["controls"] == {"motors": [0], "thrusters": []}
        start = green_circle_x(loaded)

        def play(action: list[int], steps: int) -> dict:
            socket.send_json({"type": "reset"})
            assert socket.receive_json()["t"] == 0
            for _ in range(steps):
                socket.send_json({"type": "step", "action": action})
                frame = socket.receive_json()
            return frame

        driven, idle = play(MOTOR_RIGHT, 12), play(NOOP, 12)
        assert driven["t"] == idle["t"] == 12 and driven["step_ms"] > 0
        assert green_circle_x(driven) > start + 0.05 and green_circle_x(driven) > green_circle_x(idle) + 0.05
        assert driven["scene"]["joints"][0]["drive"] == 1.0

        socket.send_json({"type": "step", "action": [3, 0, 0, 0, 0, 0]})
        assert "an action is a list of 6 integers" in socket.receive_json()["message"]
        socket.send_text("{not json")
        assert "not valid JSON" in socket.receive_json()["message"]
        socket.send_bytes(b"\x00\x01")
        assert "not binary" in socket.receive_json()["message"]
        socket.send_json({"type": "step", "agent": True})
        assert "no agent loaded" in socket.receive_json()["message"]
        socket.send_json({"type": "step", "action": NOOP})
        assert socket.receive_json()["t"] == 13  # still usable after the errors


def test_play_socket_plays_an_edited_level_until_it_is_solved(client: TestClient) -> None:
    """The editor's unsaved level plays as sent; the car solves its level and the reply says so."""
    level = level_json(client, "handmade", CAR)
    with client.websocket_connect(PLAY) as socket:
        socket.send_json({"type": "load", "level": level})
        assert socket.receive_json()["level"]["size"] == "S"
        for _ in range(200):
            socket.send_json({"type": "step", "action": MOTOR_RIGHT})
            frame = socket.receive_json()
            if frame["done"]:
                break
        assert frame["done"] and frame["outcome"] == "solved" and frame["return"] > 0.5 and frame["t"] == 0


def test_the_token_is_required_on_every_request_and_socket(levels_dir: Path) -> None:
    token = "s3cret-token"
    with studio_client(make_app(levels_dir, token=token)) as guarded:
        refused = guarded.get("/api/sets")
        assert refused.status_code == 401 and "token" in refused.json()["error"]
        assert guarded.get("/").status_code == 401
        assert guarded.get("/api/sets", headers={"X-Impulse-Token": "wrong-token"}).status_code == 401
        assert guarded.get("/api/sets", headers={"X-Impulse-Token": token}).status_code == 200
        page = guarded.get("/", params={"token": token})  # the printed address: sets the cookie for the page
        assert page.status_code == 200 and "impulse_studio_token" in page.headers["set-cookie"]
        assert guarded.get("/static/app.js").status_code == 200  # the cookie carries the token now
        guarded.cookies.clear()
        with pytest.raises(WebSocketDisconnect), guarded.websocket_connect(PLAY) as socket:
            socket.receive_json()
        with guarded.websocket_connect(f"{PLAY}?token={token}") as socket:
            socket.send_json({"type": "reset"})
            assert "no level loaded" in socket.receive_json()["message"]
        with pytest.raises(WebSocketDisconnect), guarded.websocket_connect(
                f"{PLAY}?token={token}", headers={"origin": "http://evil.example"}) as socket:
            socket.receive_json()


def test_studio_refuses_the_network_without_a_token_and_imports_no_web_stack_with_the_cli(capsys) -> None:
    assert main(["studio", "--host", "0.0.0.0"]) == 2
    assert "--token" in capsys.readouterr().err
    assert main(["studio", "--host", "0.0.0.0", "--token", "short"]) == 2
    assert "8 to 200" in capsys.readouterr().err
    assert main(["studio", "--allow-host", "evil example/"]) == 2
    assert "--allow-host 'evil example/': not a host name" in capsys.readouterr().err
    # The CLI loads a command's module only to run it (deploy.commands.Command.run_function): parsing `impulse
    # studio --help` loads no web stack and no JAX.
    loaded = subprocess.run([sys.executable, "-c", "import sys, impulse.deploy.cli; print(' '.join(sys.modules))"],
                            cwd=REPO, capture_output=True, text=True, timeout=60, check=True).stdout.split()
    assert not {name.split(".")[0] for name in loaded} & {"starlette", "uvicorn", "jax"}, loaded
    assert "impulse.deploy.commands.studio" not in loaded


@pytest.fixture(scope="module")
def tiny_pilot():
    """A small untrained entity-network agent for S levels, standing in for a checkpoint (loading one is
    `impulse eval`'s code, tested there)."""
    import jax

    from impulse.engine.env.spec import EnvParams, EnvSpec
    from impulse.learner.agent import make_agent
    from impulse.learner.config import NetworkConfig
    from impulse.studio.play import Pilot

    network = NetworkConfig(kind="entity", width=16, depth=1, entity_encoder_size=16, entity_heads=2,
                            entity_head_size=8)
    agent = make_agent(network, EnvSpec())
    return Pilot(agent, jax.jit(agent.init)(jax.random.PRNGKey(0)), EnvParams(), "tiny")


def test_watching_an_agent_steps_with_its_actions_and_refuses_levels_it_cannot_play(levels_dir: Path,
                                                                                      tiny_pilot) -> None:
    from impulse.studio.level_io import LevelInputError

    def load(path: str):
        if path != "tiny":
            raise LevelInputError(f"cannot load an agent from {path}: no config.toml")
        return tiny_pilot

    with studio_client(make_app(levels_dir, load_pilot=load, agents=["tiny"])) as client:
        assert client.get("/api/agents").json() == {"enabled": True, "checkpoints": ["tiny"], "inject_run": None}
        with client.websocket_connect(PLAY) as socket:
            socket.send_json({"type": "load", "set": "handmade", "name": CAR})
            assert socket.receive_json()["agent"] is None
            socket.send_json({"type": "agent", "checkpoint": "elsewhere"})
            assert "no config.toml" in socket.receive_json()["message"]
            socket.send_json({"type": "agent", "checkpoint": "tiny"})
            watched = socket.receive_json()
            assert watched["agent"] == "tiny" and watched["t"] == 0  # the level restarts with the agent
            for t in range(1, 4):
                socket.send_json({"type": "step", "agent": True})
                frame = socket.receive_json()
                assert frame["t"] == t and len(frame["action"]) == 6
            socket.send_json({"type": "load", "set": "handmade", "name": "m_car_bump"})
            refused = socket.receive_json()
            assert refused["type"] == "error" and "does not fit" in refused["message"]
            socket.send_json({"type": "agent", "checkpoint": None})
            assert socket.receive_json()["agent"] is None
            socket.send_json({"type": "step", "agent": True})
            assert "no agent loaded" in socket.receive_json()["message"]

        # The gallery's solve rates: every S level scored as `impulse eval` scores, the M levels listed as not fitting.
        reply = client.get("/api/solve_rates?set=handmade&checkpoint=tiny&attempts=2")
        assert reply.status_code == 200, reply.text
        rates = reply.json()
        names = [level["name"] for level in client.get("/api/levels?set=handmade").json()["levels"]]
        assert rates["agent"] == "tiny" and rates["attempts"] == 2
        assert set(rates["rates"]) == {n for n in names if n.startswith("s_")}
        assert set(rates["skipped"]) == set(names) - set(rates["rates"]) and rates["skipped"]
        assert all(r in (0.0, 0.5, 1.0) for r in rates["rates"].values())
        assert all(why == "too large for the agent's size S" for why in rates["skipped"].values()), rates
        assert client.get("/api/solve_rates?set=handmade&checkpoint=tiny&attempts=2").json() == rates  # kept
        assert client.get("/api/solve_rates?set=handmade&checkpoint=elsewhere").status_code == 422
        assert client.get("/api/solve_rates?set=handmade&checkpoint=tiny&attempts=0").status_code == 422
    with studio_client(make_app(levels_dir)) as client:
        assert client.get("/api/solve_rates?set=handmade&checkpoint=tiny").status_code == 409


def test_a_level_that_cannot_be_solved_is_saved_with_a_warning(client: TestClient, levels_dir: Path) -> None:
    """No green shape: the editor's reply and Save warn that the level cannot be solved, and Save still writes it."""
    state = edit(client, level_json(client, "handmade", THRUST), []).json()
    assert state["warnings"] == []
    green = [shape["body"] for shape in state["scene"]["polygons"] + state["scene"]["circles"]
             if shape["role"] == "green"]
    assert green, "the level has a green shape to take away"
    greyed = edit(client, state["level"], [{"op": "set_role", "body": body, "role": "neutral"} for body in green])
    assert any("cannot be solved" in w and "green" in w for w in greyed.json()["warnings"]), greyed.json()
    saved = client.post("/api/save", json={"name": "no_green", "level": greyed.json()["level"]})
    assert saved.status_code == 200, saved.text
    assert any("cannot be solved" in w and "green" in w for w in saved.json()["warnings"]), saved.json()
    assert (levels_dir / "no_green.json").is_file()
    assert client.post("/api/save", json={"name": "fine", "level": state["level"]}).json()["warnings"] == []


def test_the_run_page_reads_metrics_incrementally_and_only_of_listed_runs(tmp_path: Path, levels_dir: Path) -> None:
    """A run folder under the runs folder is listed (with the offered agent's run), its rows come back in columns
    after a given update, at most the cap per reply, without per-level evaluation columns; rows appended later
    come with the next request; a run not listed is 404."""
    from impulse.studio.runs import MAX_ROWS

    runs = tmp_path / "runs"
    (runs / "live").mkdir(parents=True)
    metrics = runs / "live" / "metrics.jsonl"

    def rows(first: int, last: int) -> str:
        return "".join(json.dumps({"update": u, "env_steps": 100 * u, "solve_rate": u / 10, "episode_return": 0.5,
                                   "eval/mean": 0.25, "eval/level/kinetix:s/a": 1.0, "note": "text",
                                   "policy_lag": None}) + "\n" for u in range(first, last + 1))

    metrics.write_text(rows(1, 5) + '{"update": 6, "solve_r')  # the last line is still being written
    with studio_client(make_app(levels_dir, agents=[str(REPO / "pretrained" / "general-s")],
                                run_folders=[runs])) as client:
        listed = client.get("/api/runs").json()
        ids = [run["id"] for run in listed["runs"]]
        assert ids[0].endswith("general-s") and listed["selected"] == ids[0] and str(runs / "live") in ids
        assert listed["runs"][0]["file"] == "curve.jsonl"
        first = client.get("/api/run/metrics", params={"run": str(runs / "live")}).json()
        assert first["total"] == 5 and first["last_update"] == 5 and not first["more"]
        assert "eval/level/kinetix:s/a" not in first["columns"] and "note" not in first["columns"]
        assert {"update", "env_steps", "solve_rate", "eval/mean"} <= set(first["columns"])
        column = first["columns"].index("solve_rate")
        assert [row[column] for row in first["rows"]] == [0.1, 0.2, 0.3, 0.4, 0.5]
        with metrics.open("a") as out:  # the cut line is finished, and more rows come
            out.write('ate": 0.6}\n' + rows(7, 9))
        later = client.get("/api/run/metrics", params={"run": str(runs / "live"), "after": 5}).json()
        assert [row[later["columns"].index("update")] for row in later["rows"]] == [6, 7, 8, 9]
        assert later["total"] == 9
        none = client.get("/api/run/metrics", params={"run": str(runs / "live"), "after": 9}).json()
        assert none["rows"] == [] and none["last_update"] == 9
        shipped = client.get("/api/run/metrics", params={"run": ids[0]}).json()
        assert len(shipped["rows"]) <= MAX_ROWS and shipped["total"] > 0
        assert client.get("/api/run/metrics", params={"run": str(tmp_path)}).status_code == 404
        assert client.get("/api/run/metrics", params={"run": str(runs / "live"), "after": "x"}).status_code == 400


def test_play_replies_are_strict_json_even_when_physics_blows_up() -> None:
    """A NaN in a reply (a scene whose physics blew up) goes out as null: the page's JSON.parse refuses NaN, and a
    reply it cannot read would leave it waiting for ever."""
    from impulse.studio.app import socket_text

    text = socket_text({"type": "state", "reward": float("nan"), "scene": {"circles": [{"centre": [1.0, math.inf]}]}})
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"type": "state", "reward": None, "scene": {"circles": [{"centre": [1.0, None]}]}}


def test_a_slow_agent_load_says_what_it_waits_for_and_loads_once(levels_dir: Path, tiny_pilot) -> None:
    """A message asking for progress gets a progress message a second while its reply takes longer (here: the agent
    loading), then its reply; without "progress" there is exactly one reply. Two sockets loading the same agent
    load it once (the studio's pilot cache), and the steps after the load compile nothing (the load did)."""
    loads = []

    def slow_load(path: str):
        loads.append(path)
        time.sleep(1.6)
        return tiny_pilot

    with studio_client(make_app(levels_dir, load_pilot=slow_load, agents=["tiny"])) as client:
        with client.websocket_connect(PLAY) as socket:
            socket.send_json({"type": "load", "set": "handmade", "name": CAR, "seq": 1})
            assert socket.receive_json()["seq"] == 1
            socket.send_json({"type": "agent", "checkpoint": "tiny", "seq": 2, "progress": True})
            progress = socket.receive_json()
            assert progress["type"] == "progress" and progress["seq"] == 2, progress
            assert progress["what"] == "loading the agent tiny" and progress["elapsed_s"] >= 1.0
            reply = socket.receive_json()
            while reply["type"] == "progress":  # a busy machine may take another second
                reply = socket.receive_json()
            assert reply["agent"] == "tiny" and reply["seq"] == 2
            started = time.perf_counter()
            socket.send_json({"type": "step", "agent": True, "seq": 3, "progress": True})
            assert socket.receive_json()["type"] == "state"
            assert time.perf_counter() - started < 1.0, "the first agent step compiled: the load should have"
        with client.websocket_connect(PLAY) as socket:
            socket.send_json({"type": "agent", "checkpoint": "tiny"})
            assert socket.receive_json() == {"type": "agent", "agent": "tiny", "seq": None}
        assert loads == ["tiny"]
        assert client.get("/api/solve_rates/progress?set=handmade&checkpoint=tiny").json() == {"progress": None}
