"""The curriculum service over a real bus (zenoh on loopback; the test plays the actors and a person at the
command line): level batches on request, results applied, live knobs validated and applied at the next sample,
malformed input refused while it keeps serving, a restart from its checkpoint losing no buffered level, and a level
a person sends in (`impulse curriculum inject`, or the studio's editor) put into the buffer or refused with the
reason."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from starlette.testclient import TestClient

from impulse.bus.codec import Kind, decode, encode
from impulse.bus.config import BusConfig
from impulse.bus.control import control_reply, control_request
from impulse.bus.levels import LEVEL_QUERY_TIMEOUT_S, WAIT_PARAMETER, encode_level_results
from impulse.bus.session import Bus
from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods import make_curriculum
from impulse.curriculum.service import CurriculumService
from impulse.curriculum.state import ORIGIN_NEW
from impulse.curriculum.wire import (
    level_batch_from_message,
    level_batch_schema,
    level_batch_template,
)
from impulse.engine.env.spec import EnvParams
from impulse.engine.levels import handmade
from impulse.engine.levels.level import level_id_values, level_id_words
from impulse.learner.checkpoint import CURRICULUM, Checkpointer
from impulse.studio.app import make_app
from impulse.studio.console import CurriculumLink
from impulse.studio.level_io import load_document
from tests.support.checkpoint_damage import corrupt_newest
from tests.support.curriculum_service import BATCH, SPEC, resolve_knobs, start_service
from tests.support.launch_procs import free_port

RUN = "curriculum-test"


ASK_TIMEOUT_S = 90.0
"""How long a query waits for the service's answer: a first answer compiles the sample program, which took 51 s
on the loaded 2-core CI machine with a cold cache (2026-12-03)."""


def serve_until(service: CurriculumService, asked, timeout_s: float = ASK_TIMEOUT_S + 30.0):
    """Run `asked()` (a blocking bus query) in a thread while the service polls in this one; what `asked` raised
    is raised here."""
    box: dict = {}

    def ask() -> None:
        try:
            box["answer"] = asked()
        except BaseException as err:  # noqa: BLE001 - handed to the test's thread below
            box["error"] = err

    thread = threading.Thread(target=ask)
    thread.start()
    deadline = time.monotonic() + timeout_s
    while thread.is_alive():
        assert time.monotonic() < deadline, "the service did not answer"
        service.cycle()
        time.sleep(0.002)
    thread.join()
    if "error" in box:
        raise box["error"]
    return box["answer"]


@pytest.fixture(scope="module")
def hub():
    port = free_port()
    config = BusConfig(hub=f"tcp/127.0.0.1:{port}")
    with Bus(config, RUN, "operator", "hub", listen=True) as hub_bus:
        yield hub_bus


def test_service_serves_applies_tunes_refuses_and_restarts(hub, tmp_path):
    template = level_batch_template(SPEC.sizes, BATCH)
    schema = level_batch_schema(template)
    with Bus(hub.config, RUN, "curriculum", "curriculum") as bus, Bus(hub.config, RUN, "actor", "actor-0") as actor:
        service, checkpoints = start_service(bus, tmp_path / "ckpt", resume=False)
        results = actor.publisher(actor.keys.levels_results("actor-0"))
        assert actor.wait_matching(results, 10)

        def sample():
            [payload] = actor.get(actor.keys.levels_sample, parameters=f"n={BATCH}", timeout_s=ASK_TIMEOUT_S)
            return level_batch_from_message(decode(payload, run=RUN, kinds=Kind.LEVELS), schema, template)

        def knobs(**request):
            [payload] = actor.get(actor.keys.curriculum_knobs, payload=control_request(**request),
                                  timeout_s=ASK_TIMEOUT_S)
            return control_reply(payload)

        first = serve_until(service, sample)
        assert (np.asarray(first.origin) == ORIGIN_NEW).all() and np.asarray(first.train).all()

        # A query that waited in the queue for half the wait its asker states (the service busy elsewhere) is refused
        # at once rather than served after its asker has given up: a service serving only such queries never catches
        # up. The test's other queries state no wait, so they never expire however slow the service.
        late = threading.Thread(target=lambda: actor.get(
            actor.keys.levels_sample, parameters=f"n={BATCH};{WAIT_PARAMETER}={LEVEL_QUERY_TIMEOUT_S}",
            timeout_s=LEVEL_QUERY_TIMEOUT_S))
        asked_at = time.monotonic()
        late.start()
        time.sleep(LEVEL_QUERY_TIMEOUT_S / 2 + 1.5)  # the extra second and a half: the query's way through the hub
        served = service.samples
        while late.is_alive():
            service.cycle()
            time.sleep(0.01)
        assert time.monotonic() - asked_at < LEVEL_QUERY_TIMEOUT_S, "the asker should hear the refusal, not time out"
        assert service.samples == served and service.status()["dropped_expired_queries"] == 1
        ids = level_id_values(np.asarray(first.levels.level_id))

        # Results for the batch: every level gets two episodes, one solved, so each is scored and inserted.
        arrays = {"level_id": np.stack([level_id_words(int(i)) for i in ids]),
                  "episodes": np.full(BATCH, 2, np.int32), "solved": np.ones(BATCH, np.int32),
                  "return_sum": np.ones(BATCH, np.float32), "return_max": np.ones(BATCH, np.float32),
                  "value_sum": np.zeros(BATCH, np.float32), "pvl_sum": np.zeros(BATCH, np.float32),
                  "l1_sum": np.zeros(BATCH, np.float32), "policy_version": np.full(BATCH, 3, np.int32)}
        actor.stamp.acting_for(epoch=1, policy_version=3)
        results.put(encode_level_results(actor.stamp, arrays, seq=1))
        # Malformed: garbage bytes, and well-formed arrays with more solved than played episodes.
        results.put(b"not a frame")
        results.put(encode(Kind.LEVEL_RESULTS, {**arrays, "solved": np.full(BATCH, 5, np.int32)}, run=RUN))
        deadline = time.monotonic() + 20
        while service.result_messages < 1 or sum(bus.rejects.counts().values()) < 2:
            assert time.monotonic() < deadline, (service.result_messages, bus.rejects.counts())
            service.cycle()
            time.sleep(0.01)
        assert sorted(bus.rejects.counts()) == ["schema", "truncated"]
        buffered = set(level_id_values(np.asarray(service.state.buffer.levels.level_id))[
            np.asarray(service.state.buffer.filled)])
        assert buffered == set(ids)

        # A live knob takes effect at the next sample: robust PLR marks new levels as evaluated only.
        reply = serve_until(service, lambda: knobs(set=["robust=true", "replay_prob=0"]))
        assert reply["ok"] and reply["changed"] == {"robust": [False, True]} and reply["knobs"]["robust"] is True
        after = serve_until(service, sample)
        assert not np.asarray(after.train).any()

        # Bad values and fixed keys are refused with the config system's messages; nothing changes.
        for assignment, message in (("replay_prob=2", "replay_prob must be in [0, 1]"),
                                    ("temperature=warm", "expects a finite float"),
                                    ("replay_prb=0.1", "did you mean 'replay_prob'"),
                                    ("buffer_size=8", "fixed for the life of a run")):
            reply = serve_until(service, lambda a=assignment: knobs(set=[a]))
            assert not reply["ok"] and message in reply["error"], reply
        assert serve_until(service, knobs)["knobs"]["replay_prob"] == 0.0

        staged = set(level_id_values(np.asarray(service.state.staging.levels.level_id))[
            np.asarray(service.state.staging.staged)])
        service.save()
        samples_saved = service.samples
        serve_until(service, sample)
        service.save()  # a newer checkpoint, which the test then damages
        checkpoints.close()
        corrupted = corrupt_newest(tmp_path / "ckpt", "curriculum")
        assert corrupted == service.step

        # The restarted service sets the damaged checkpoint aside (kept) and resumes from the one before.
        restarted, checkpoints = start_service(bus, tmp_path / "ckpt", resume=True)
        state = restarted.state
        assert set(level_id_values(np.asarray(state.buffer.levels.level_id))[np.asarray(state.buffer.filled)]) \
            == buffered
        assert set(level_id_values(np.asarray(state.staging.levels.level_id))[np.asarray(state.staging.staged)]) \
            == staged
        assert restarted.live_knobs()["robust"] is True and restarted.samples == samples_saved
        assert (tmp_path / "ckpt-corrupt" / str(corrupted)).is_dir()
        checkpoints.close()


def test_new_levels_pass_the_noop_filter_ahead_of_the_requests(hub, tmp_path):
    template = level_batch_template(SPEC.sizes, BATCH)
    schema = level_batch_schema(template)
    config = CurriculumConfig(method="dr", noop_filter=True, levels_ahead=2)
    with Bus(hub.config, RUN, "curriculum", "curriculum") as bus, Bus(hub.config, RUN, "actor", "actor-0") as actor:
        checkpoints = Checkpointer(tmp_path / "ckpt")
        service = CurriculumService(make_curriculum(config, SPEC, EnvParams(), BATCH), bus, checkpoints, "",
                                    resolve_knobs, item=CURRICULUM)
        service.start()  # returns once the first filtered batch is made
        assert service.maker is not None and service.maker.made >= 1

        def sample():
            [payload] = actor.get(actor.keys.levels_sample, parameters=f"n={BATCH}", timeout_s=ASK_TIMEOUT_S)
            return level_batch_from_message(decode(payload, run=RUN, kinds=Kind.LEVELS), schema, template)

        served = []
        for _ in range(3):
            deadline = time.monotonic() + 60
            while service.maker.ready < 1:
                assert time.monotonic() < deadline, "no filtered batch made ahead"
                time.sleep(0.01)
            batch = serve_until(service, sample)
            assert (np.asarray(batch.origin) == ORIGIN_NEW).all()
            served.append(set(level_id_values(np.asarray(batch.levels.level_id)).tolist()))
        assert len(set.union(*served)) == 3 * BATCH
        ahead = service.status()["levels_ahead"]
        assert ahead["made"] >= 3 and ahead["unfiltered"] == 0, ahead
        service.close()
        assert not service.maker.running
        checkpoints.close()


def test_a_level_sent_in_enters_the_buffer_or_is_refused_with_the_reason(hub, tmp_path):
    with Bus(hub.config, RUN, "curriculum", "curriculum") as bus, Bus(hub.config, RUN, "operator", "cli") as person:

        def inject(document) -> dict:
            [payload] = person.get(person.keys.curriculum_inject, payload=control_request(level=document),
                                   timeout_s=ASK_TIMEOUT_S)
            return control_reply(payload)

        service, checkpoints = start_service(bus, tmp_path / "ckpt", resume=False)
        car = json.loads(handmade.level_file("s_easy_car_right").read_text())
        reply = serve_until(service, lambda: inject(car))
        assert reply["ok"] and reply["slot"] == 0 and not reply["evicted"], reply
        buffer = service.state.buffer
        assert np.asarray(buffer.filled).sum() == 1 and service.injected == 1 and service.status()["injected"] == 1
        assert service.status()["dropped_queries"] == 0
        car_id = reply["level_id"]
        assert f"{int(level_id_values(np.asarray(buffer.levels.level_id))[0]):016x}" == car_id

        for document, reason in ((car, "in the buffer already"),
                                 (json.loads(handmade.level_file("m_car_bump").read_text()), "too large for the size"),
                                 ({"env_state": 3}, "env_state missing or not an object"),
                                 ([1, 2], "the top level must be an object")):
            reply = serve_until(service, lambda d=document: inject(d))
            assert not reply["ok"] and reason in reply["error"], (reason, reply)
        assert service.injected == 1

        # The studio's editor sends a level the same way (`impulse studio --run RUN_DIR`: POST /api/inject), and
        # its Curriculum page shows the buffer, draws its levels and changes knobs through the service.
        link = CurriculumLink(hub.config, RUN, SPEC)
        with TestClient(make_app(tmp_path / "levels", curriculum=link), base_url="http://127.0.0.1") as client:
            assert client.get("/api/agents").json()["inject_run"] == RUN
            hop = json.loads(handmade.level_file("s_hop_over").read_text())
            sent = serve_until(service, lambda: client.post("/api/inject", json={"level": hop}))
            assert sent.status_code == 200 and sent.json()["slot"] == 1, sent.text
            again = serve_until(service, lambda: client.post("/api/inject", json={"level": hop}))
            assert again.status_code == 422 and "in the buffer already" in again.json()["error"], again.text

            page = serve_until(service, lambda: client.get("/api/curriculum?top=5"))
            assert page.status_code == 200, page.text
            report = page.json()
            ids = {f"{int(i):016x}" for i in level_id_values(np.asarray(service.state.buffer.levels.level_id))[:2]}
            assert report["run"] == RUN and {row["level_id"] for row in report["top"]} == ids, report["top"]
            # the car came over the bus from `impulse curriculum inject` (the buffer keeps no origin, so it reads as
            # new); the studio remembers the level it sent itself
            origins = {row["level_id"]: row["origin"] for row in report["top"]}
            assert origins == {car_id: "new", sent.json()["level_id"]: "injected"}, origins
            png = client.get(f"/api/curriculum/thumbnail?level_id={report['top'][0]['level_id']}")
            assert png.status_code == 200 and png.content.startswith(b"\x89PNG")
            assert client.get("/api/curriculum/thumbnail?level_id=00").status_code == 404

            # The run's buffer is a gallery set as well: its levels, best first, open as level files.
            listed = serve_until(service, lambda: client.get(f"/api/levels?set=run:{RUN}"))
            assert listed.status_code == 200, listed.text
            names = [level["name"] for level in listed.json()["levels"]]
            assert [name.split("_")[1] for name in names] == [row["level_id"] for row in report["top"]]
            opened = client.get(f"/api/level?set=run:{RUN}&name={names[0]}").json()
            assert np.array_equal(load_document(opened).level.level_id, level_id_words(int(names[0].split("_")[1], 16)))
            assert any(s["id"] == f"run:{RUN}" for s in client.get("/api/sets").json()["sets"])

            before = report["knobs"]["replay_prob"]
            changed = serve_until(service, lambda: client.post("/api/curriculum/knobs",
                                                               json={"set": [f"replay_prob={1 - before}"]}))
            assert changed.status_code == 200 and "replay_prob" in changed.json()["changed"], changed.text
            refused = serve_until(service, lambda: client.post("/api/curriculum/knobs",
                                                               json={"set": ["replay_prob=7"]}))
            assert refused.status_code == 422 and "replay_prob" in refused.json()["error"], refused.text
            knobs = serve_until(service, lambda: client.post("/api/curriculum/knobs", json={}))
            assert knobs.json()["knobs"]["replay_prob"] == pytest.approx(1 - before)
        assert service.injected == 2
        # A run whose service does not answer: every curriculum route says so (503), and the studio goes on.
        silent = CurriculumLink(hub.config, "no-such-run", SPEC, timeout_s=1.0)
        with TestClient(make_app(tmp_path / "levels", curriculum=silent), base_url="http://127.0.0.1") as client:
            for reply in (client.get("/api/curriculum?top=5"), client.post("/api/inject", json={"level": hop}),
                          client.post("/api/curriculum/knobs", json={}), client.get("/api/levels?set=run:no-such-run")):
                assert reply.status_code == 503 and "no-such-run" in reply.json()["error"], reply.text
            assert client.get("/api/sets").status_code == 200
        service.save()  # the injections are checkpointed with the buffer
        checkpoints.close()
        restarted, checkpoints = start_service(bus, tmp_path / "ckpt", resume=True)
        assert restarted.injected == 2 and np.asarray(restarted.state.buffer.filled).sum() == 2
        checkpoints.close()
