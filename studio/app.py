"""The studio's web app: `make_app` builds the Starlette application that `impulse studio` serves with uvicorn.

Routes (all JSON unless said otherwise; errors are {"error": message, "problems": [...]} with a 4xx status, and
the server keeps running):

- `GET /`: the page (`static/index.html`; its scripts and styles under `/static/`);
- `GET /api/sets`: the level sets (`library.Library.sets`); `GET /api/levels?set=S`: a set's levels with size,
  counts and thumbnail address (the set "run:NAME" of a linked run is its buffer, fetched anew each time);
  `GET /api/thumbnail?set=S&name=N`: the level drawn as a PNG;
- `GET /api/level?set=S&name=N`: the level as a Kinetix level file (JSON);
- `POST /api/edit` {"level", "ops", "size"?}: the level after the editor's operations (`editing`), with its scene,
  counts and the problems `validate_scene` finds (ops [] just draws a level); with "size" ("s", "m", "l") the level
  is first moved into that size (into a larger one with more slots; into a smaller one with the unused slots
  dropped, or a refusal naming what the level uses that does not fit);
- `POST /api/validate` {"level", "size"?}: 200 when `impulse levels validate [--size]` would accept it, else 422
  with every problem; `POST /api/save` {"name", "level", "size"?}: validate, then write `<levels-dir>/<name>.json`;
- `GET /api/agents`: the checkpoints offered for watching, and the run a level can be sent to;
- `GET /api/solve_rates?set=S&checkpoint=C&attempts=N`: how often that agent solves each level of the set
  (`solve_rates`, `impulse eval`'s scoring), 409 when the studio cannot load agents;
  `GET /api/solve_rates/progress?...` (the same query): how far that scoring is while it runs;
- `GET /api/runs`: the runs whose learning curves the Run page shows (`runs`); `GET /api/run/metrics?run=R&after=U`:
  that run's metrics rows after update U, in columns, at most `runs.MAX_ROWS` per reply;
- `POST /api/inject` {"level"}: send the level into the running curriculum of `--run`'s run (`console`): its
  reply, or 422 with the service's reason;
- `GET /api/curriculum?top=K`: that curriculum's buffer report with its K best levels, every level's score and
  solve rate for the charts, and the studio's history of its counters (`console`);
  `GET /api/curriculum/thumbnail?level_id=ID`: one of those levels as a PNG;
  `POST /api/curriculum/knobs` {"set": ["replay_prob=0.8", ...]}: change live knobs (or, without "set", read
  them), 422 with the service's reason when refused. All four answer 409 when the studio has no run and 503
  when no curriculum service answers (one handler each, for every route);
- `WebSocket /ws/play`: play and watch (`protocol`); a message with "progress": true gets a progress message every
  second while its reply takes longer than one (what it is doing: loading, compiling on first use).

Every request and handshake first passes `security.Guard`: the Host allow-list, the access token, the same-origin
and content-type checks and the body cap (`MAX_BODY_BYTES`: a larger Content-Length is refused before reading, any
other body is counted as it streams in; 413 either way). `UVICORN_SETTINGS` are the server settings `impulse
studio` serves with (the same cap on WebSocket messages). A save that cannot be written (a full disk, a read-only
folder) answers 507 naming the file and the free space.

Engine work (loading, drawing, compiling, stepping) runs in worker threads, so one slow request (a first
compilation) never stalls the others. A save or an edit of a level that can never be solved (no green shape, ...)
carries `warnings` (`solvable`); the level is saved all the same.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from impulse.curriculum.client import CurriculumUnreachable
from impulse.engine.levels.drawing import scene_drawing
from impulse.engine.levels.summary import size_class
from impulse.engine.physics.validate import validate_scene
from impulse.studio.console import CurriculumLink, CurriculumRefused, json_ready
from impulse.studio.editing import apply_edits
from impulse.studio.level_io import (
    LevelInputError,
    StorageError,
    level_document,
    level_problems,
    load_document,
    load_file,
    parse_size,
    save_document,
)
from impulse.studio.library import SAVED, Library, UnknownLevel, level_counts
from impulse.studio.protocol import PilotCache, PilotLoader, PlayConnection
from impulse.studio.runs import MAX_ROWS, Runs
from impulse.studio.scene import actuator_settings, scene_json
from impulse.studio.security import BodyTooLarge, Guard
from impulse.studio.solvable import unsolvable_reasons
from impulse.studio.solve_rates import DEFAULT_ATTEMPTS, SolveRates

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
MAX_BODY_BYTES = 8 * 2**20
"""The largest request body or WebSocket message the studio reads (Kinetix's largest level files are about 50 KB)."""
UVICORN_SETTINGS: dict[str, Any] = {"ws_max_size": MAX_BODY_BYTES}
"""Settings for `uvicorn.run` / `uvicorn.Config` beyond host and port, for every server of the studio: a WebSocket
message over the cap closes the socket (code 1009) without being held whole."""


MAX_BUFFER_ROWS = 256
"""The most buffer levels the Curriculum page asks for at once (each is drawn)."""
BUFFER_SET_LEVELS = 64
"""The buffer levels the gallery's set of a linked run holds: the best by score."""
PROGRESS_EVERY_S = 1.0
"""A play message whose reply takes longer than this gets a progress message this often (when it asks for them)."""
SLOW_PLAY_S = 5.0
"""A play message that takes longer than this is logged, with what it was doing."""
RUN_FOLDERS = (Path("runs"),)
"""Where the Run page looks for runs besides the offered agents' (`run_dir = "runs/{name}"` by default)."""
IMMUTABLE = {"Cache-Control": "private, max-age=86400, immutable"}
"""For a buffer level's thumbnail: its id is its content's, so the picture of an id never changes."""


class RequestError(ValueError):
    """A request the studio cannot read (not JSON, too large, a missing field): HTTP 400."""


class PageGone(Exception):
    """The play socket's page went away while its message was being handled."""


class NoRun(LookupError):
    """A request this studio was not started for (a curriculum request without a run, solve rates without agents):
    HTTP 409."""


def _error(status: int, message: str, problems: list[str] | None = None) -> JSONResponse:
    return JSONResponse({"error": message, "problems": problems or []}, status_code=status)


def _json(text: str | bytes | bytearray) -> Any:
    """The JSON value in a request body or a socket message; `RequestError` saying why it is not JSON."""
    try:
        return json.loads(text)
    except RecursionError:
        raise RequestError("not valid JSON: nested too deeply to read") from None
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError, an integer of too many digits
        raise RequestError(f"not valid JSON: {err}") from None


async def _body(request: Request) -> dict[str, Any]:
    """The request's JSON object, read in chunks as it streams in: `BodyTooLarge` (413) as soon as it passes
    `MAX_BODY_BYTES`, so no more than that is ever held (`security.Guard` counts too, and refuses a larger
    Content-Length before anything is read)."""
    raw = bytearray()
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > MAX_BODY_BYTES:
            raise BodyTooLarge(MAX_BODY_BYTES)
    body = _json(raw)
    if not isinstance(body, dict):
        raise RequestError(f"the request body must be a JSON object, got {type(body).__name__}")
    return body


def _query(request: Request, *names: str) -> list[str]:
    missing = [name for name in names if not request.query_params.get(name)]
    if missing:
        raise RequestError(f"missing query parameter(s): {', '.join(missing)}")
    return [request.query_params[name] for name in names]


def _edited(body: dict[str, Any]) -> dict[str, Any]:
    """The reply of POST /api/edit: the edited level, its scene, its joints' and thrusters' settings, counts, size
    and problems."""
    if "level" not in body:
        raise RequestError("edit needs \"level\" (a Kinetix level JSON object) and \"ops\" (a list)")
    loaded = load_document(body["level"], parse_size(body.get("size")), validate=False, compact=True)
    level = apply_edits(loaded.level, loaded.sizes, body.get("ops", []))
    return {"level": level_document(loaded, level), "scene": scene_json(scene_drawing(level)),
            "actuators": actuator_settings(level), "size": size_class(loaded.sizes),
            "counts": level_counts(level.state, loaded.sizes),
            "problems": validate_scene(level.state), "warnings": unsolvable_reasons(level, loaded.sizes)}


def socket_text(reply: dict[str, Any]) -> str:
    """A play reply as strict JSON: a NaN or an infinity (a scene whose physics blew up) is sent as null, since a
    browser's JSON.parse refuses them, and a reply the page cannot read would leave it waiting for ever."""
    try:
        return json.dumps(reply, allow_nan=False)
    except ValueError:
        log.warning("studio: a play reply held NaN or infinity; sent as null")
        return json.dumps(json_ready(reply), allow_nan=False)


async def answer_play(websocket: WebSocket, connection: PlayConnection, message: Any, seq: Any,
                      progress: bool) -> dict[str, Any]:
    """`connection.handle(message)` in a worker thread; while it runs, with `progress`, a progress message every
    PROGRESS_EVERY_S saying what the connection is doing (`PlayConnection.phase`) and for how long."""
    work = asyncio.ensure_future(run_in_threadpool(connection.handle, message))
    started = time.monotonic()
    while not (await asyncio.wait({work}, timeout=PROGRESS_EVERY_S))[0]:
        if not progress:
            continue
        try:
            await websocket.send_text(json.dumps({
                "type": "progress", "seq": seq, "what": connection.phase or "working",
                "elapsed_s": round(time.monotonic() - started, 1)}))
        except (WebSocketDisconnect, RuntimeError):  # the work finishes in its thread; nobody reads its result
            work.add_done_callback(lambda done: done.cancelled() or done.exception())
            raise PageGone() from None
    elapsed = time.monotonic() - started
    if elapsed > SLOW_PLAY_S:
        kind = message.get("type") if isinstance(message, dict) else None
        log.info("studio: play message %r took %.1f s (last: %s)", kind, elapsed, connection.phase)
    return work.result()


def make_app(
    levels_dir: Path,
    sources: Sequence[str] = (),
    *,
    token: str | None = None,
    host: str = "127.0.0.1",
    allow_hosts: Sequence[str] = (),
    load_pilot: PilotLoader | None = None,
    agents: Sequence[str] = (),
    curriculum: CurriculumLink | None = None,
    run_folders: Sequence[Path] = RUN_FOLDERS,
) -> Starlette:
    """The studio app: levels from the hand-made and Kinetix sets, `levels_dir` (where it saves) and `sources`
    (folders, files or glob patterns); `token` required on every request when given (`impulse studio` always
    gives one; None is for callers that serve nothing on a socket, such as Starlette's TestClient); `host` the
    address it is served on and `allow_hosts` more names it answers to (`security.Guard`: every other Host is
    refused, against DNS rebinding); `load_pilot` loads a
    checkpoint to watch (None: watching is off), `agents` the checkpoints the page offers; `curriculum` links to
    a running run's curriculum service (the Curriculum page and "Send to run"; None: no run); `run_folders` hold
    runs (one per subfolder) whose learning curves the Run page shows, besides those of `agents`."""
    # A linked run's buffer is a gallery set too: a folder of level files that each listing rewrites from the
    # service (`CurriculumLink.snapshot`), so its levels open, play and score as any others do.
    buffer_folder, buffer_set, folders = None, None, {}
    if curriculum is not None:
        buffer_folder = tempfile.TemporaryDirectory(prefix="impulse-studio-buffer-")
        buffer_set = f"run:{curriculum.run}"
        folders[buffer_set] = (f"Curriculum buffer of run {curriculum.run} (live: its best {BUFFER_SET_LEVELS} "
                               "levels by score)", Path(buffer_folder.name))
    library = Library(Path(levels_dir), tuple(sources), folders)
    pilots = PilotCache(load_pilot) if load_pilot is not None else None  # one load per agent, shared
    solve_rates = SolveRates(library, pilots) if pilots is not None else None
    runs = Runs(agents, run_folders)

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html")

    async def sets(request: Request) -> Response:
        found = await run_in_threadpool(library.sets)
        return JSONResponse({"sets": [{"id": s.id, "title": s.title, "unavailable": s.unavailable} for s in found]})

    async def levels(request: Request) -> Response:
        [set_id] = _query(request, "set")
        if set_id == buffer_set:
            await run_in_threadpool(linked().snapshot, folders[set_id][1], BUFFER_SET_LEVELS)
        entries = await run_in_threadpool(library.summaries, set_id)
        for entry in entries:
            entry["thumbnail"] = "/api/thumbnail?" + urlencode({"set": set_id, "name": entry["name"]})
        return JSONResponse({"set": set_id, "levels": entries})

    async def thumbnail(request: Request) -> Response:
        set_id, name = _query(request, "set", "name")
        png = await run_in_threadpool(library.thumbnail, set_id, name)
        return Response(png, media_type="image/png", headers={"Cache-Control": "no-cache"})

    async def level(request: Request) -> Response:
        set_id, name = _query(request, "set", "name")

        def read() -> dict[str, Any]:
            return level_document(load_file(library.path(set_id, name)))

        return JSONResponse(await run_in_threadpool(read))

    async def edit(request: Request) -> Response:
        return JSONResponse(await run_in_threadpool(_edited, await _body(request)))

    async def validate(request: Request) -> Response:
        body = await _body(request)

        def check() -> dict[str, Any]:
            sizes = parse_size(body.get("size"))
            problems = level_problems(body.get("level"), sizes)
            if problems:
                raise LevelInputError("the level is not valid", problems)
            loaded = load_document(body["level"], sizes)
            return {"valid": True, "size": size_class(loaded.file_sizes or loaded.sizes),
                    "counts": level_counts(loaded.state, loaded.sizes)}

        return JSONResponse(await run_in_threadpool(check))

    async def save(request: Request) -> Response:
        body = await _body(request)
        path, loaded = await run_in_threadpool(save_document, body.get("level"), body.get("name"), library.levels_dir,
                                               body.get("size"))
        log.info("studio: saved %s", path)
        return JSONResponse({"saved": {"set": SAVED, "name": path.stem}, "path": str(path),
                             "size": size_class(loaded.sizes),
                             "warnings": unsolvable_reasons(loaded.level, loaded.sizes)})

    async def agent_list(request: Request) -> Response:
        return JSONResponse({"enabled": load_pilot is not None, "checkpoints": list(agents),
                             "inject_run": curriculum.run if curriculum is not None else None})

    def scoring(request: Request) -> tuple[SolveRates, str, str, int]:
        set_id, checkpoint = _query(request, "set", "checkpoint")
        attempts = request.query_params.get("attempts", str(DEFAULT_ATTEMPTS))
        if not attempts.isdigit():
            raise RequestError(f"attempts must be a whole number, got {attempts!r}")
        if solve_rates is None:
            raise NoRun("this studio cannot load agents")
        return solve_rates, set_id, checkpoint, int(attempts)

    async def agent_rates(request: Request) -> Response:
        rates, set_id, checkpoint, attempts = scoring(request)
        return JSONResponse(await run_in_threadpool(rates.rates, set_id, checkpoint, attempts))

    async def agent_rates_progress(request: Request) -> Response:
        rates, set_id, checkpoint, attempts = scoring(request)
        return JSONResponse({"progress": rates.progress(set_id, checkpoint, attempts)})

    async def run_list(request: Request) -> Response:
        listed = await run_in_threadpool(runs.listing)
        return JSONResponse({"runs": listed, "selected": listed[0]["id"] if listed else None})

    async def run_metrics(request: Request) -> Response:
        [run_id] = _query(request, "run")
        after, limit = request.query_params.get("after", ""), request.query_params.get("limit", str(MAX_ROWS))
        try:
            after_update = float(after) if after else -math.inf
        except ValueError:
            raise RequestError(f"after must be a number (an update), got {after!r}") from None
        if not limit.isdigit():
            raise RequestError(f"limit must be a whole number, got {limit!r}")
        return JSONResponse(await run_in_threadpool(runs.metrics, run_id, after_update, int(limit)))

    def linked() -> CurriculumLink:
        if curriculum is None:
            raise NoRun("this studio has no running curriculum: start it with --run RUN_DIR of a run on random "
                        "levels")
        return curriculum

    async def inject(request: Request) -> Response:
        body = await _body(request)
        link = linked()
        if not isinstance(body.get("level"), dict):
            raise RequestError('inject needs "level": a Kinetix level JSON object')
        reply = await run_in_threadpool(link.inject, body["level"])
        if not reply.get("ok"):
            raise CurriculumRefused(f"the curriculum refused the level: {reply.get('error')}")
        log.info("studio: sent a level into run %s's curriculum: slot %s", link.run, reply.get("slot"))
        return JSONResponse(reply)

    async def buffer(request: Request) -> Response:
        link = linked()
        top = request.query_params.get("top", "24")
        if not top.isdigit() or not 1 <= int(top) <= MAX_BUFFER_ROWS:
            raise RequestError(f"top must be a whole number from 1 to {MAX_BUFFER_ROWS}, got {top!r}")
        points = request.query_params.get("points", "1") != "0"
        return JSONResponse(await run_in_threadpool(link.buffer, int(top), points))

    async def buffer_thumbnail(request: Request) -> Response:
        [level_id] = _query(request, "level_id")
        png = await run_in_threadpool(linked().thumbnail, level_id)
        return Response(png, media_type="image/png", headers=IMMUTABLE)

    async def knobs(request: Request) -> Response:
        body = await _body(request)
        link = linked()
        assignments = body.get("set")
        if assignments is not None and (not isinstance(assignments, list)
                                        or not all(isinstance(a, str) for a in assignments)):
            raise RequestError('"set" must be a list of "knob=value" strings')
        reply = await run_in_threadpool(link.knobs, assignments)
        if not reply.get("ok"):
            raise CurriculumRefused(f"the curriculum refused: {reply.get('error')}")
        if assignments:
            log.info("studio: run %s's curriculum knobs: %s", link.run, reply.get("changed"))
        return JSONResponse(reply)

    async def play(websocket: WebSocket) -> None:
        await websocket.accept()
        connection = PlayConnection(library, pilots)
        while True:
            received = await websocket.receive()
            if received["type"] == "websocket.disconnect":
                return
            seq = None
            try:
                if received.get("text") is None:
                    raise RequestError("messages are JSON text, not binary")
                if len(received["text"]) > MAX_BODY_BYTES:  # uvicorn refuses these first (UVICORN_SETTINGS)
                    raise RequestError(f"a message may be at most {MAX_BODY_BYTES:,} characters")
                message = _json(received["text"])
                seq = message.get("seq") if isinstance(message, dict) else None
                progress = isinstance(message, dict) and message.get("progress") is True
                reply = await answer_play(websocket, connection, message, seq, progress)
            except PageGone:
                return
            except (RequestError, LevelInputError, UnknownLevel, ValueError) as err:
                reply = {"type": "error", "message": str(err)}
            except Exception as err:  # the connection and the server go on; the log has the traceback
                log.exception("studio: play message failed")
                reply = {"type": "error", "message": f"internal error: {type(err).__name__}: {err}"}
            reply["seq"] = seq
            try:
                await websocket.send_text(socket_text(reply))
            except (WebSocketDisconnect, RuntimeError):  # the page went away mid-reply
                return

    async def bad_input(request: Request, err: Exception) -> Response:
        problems = err.problems if isinstance(err, LevelInputError) else []
        message = err.message if isinstance(err, LevelInputError) else str(err)
        return _error(422, message, problems)

    async def bad_request(request: Request, err: Exception) -> Response:
        return _error(400, str(err))

    async def too_large(request: Request, err: Exception) -> Response:
        # Closing the connection leaves the rest of the upload unread (uvicorn would otherwise read and drop it).
        return JSONResponse({"error": str(err), "problems": []}, status_code=413, headers={"Connection": "close"})

    async def gone(request: Request, err: Exception) -> Response:
        # The client left mid-request (an upload given up on): nothing failed, and nobody reads the reply.
        return Response(status_code=400)

    async def storage_failed(request: Request, err: Exception) -> Response:
        log.warning("studio: %s", err)
        return _error(507, str(err))

    async def no_run(request: Request, err: Exception) -> Response:
        return _error(409, str(err))

    async def curriculum_refused(request: Request, err: Exception) -> Response:
        return _error(422, str(err))

    async def curriculum_unreachable(request: Request, err: Exception) -> Response:
        return _error(503, str(err))

    async def not_found(request: Request, err: Exception) -> Response:
        return _error(404, str(err.args[0]) if err.args else "not found")

    async def failed(request: Request, err: Exception) -> Response:
        log.exception("studio: %s %s failed", request.method, request.url.path, exc_info=err)
        return _error(500, f"internal error: {type(err).__name__}: {err}")

    routes = [
        Route("/", index),
        Route("/api/sets", sets),
        Route("/api/levels", levels),
        Route("/api/thumbnail", thumbnail, name="thumbnail"),
        Route("/api/level", level),
        Route("/api/edit", edit, methods=["POST"]),
        Route("/api/validate", validate, methods=["POST"]),
        Route("/api/save", save, methods=["POST"]),
        Route("/api/agents", agent_list),
        Route("/api/solve_rates", agent_rates),
        Route("/api/solve_rates/progress", agent_rates_progress),
        Route("/api/runs", run_list),
        Route("/api/run/metrics", run_metrics),
        Route("/api/inject", inject, methods=["POST"]),
        Route("/api/curriculum", buffer),
        Route("/api/curriculum/thumbnail", buffer_thumbnail),
        Route("/api/curriculum/knobs", knobs, methods=["POST"]),
        WebSocketRoute("/ws/play", play),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    app = Starlette(routes=routes, exception_handlers={
        LevelInputError: bad_input, RequestError: bad_request, BodyTooLarge: too_large, StorageError: storage_failed,
        ClientDisconnect: gone, NoRun: no_run, UnknownLevel: not_found,
        CurriculumRefused: curriculum_refused, CurriculumUnreachable: curriculum_unreachable, Exception: failed,
    })
    app.add_middleware(Guard, token=token, host=host, allow_hosts=tuple(allow_hosts), max_body_bytes=MAX_BODY_BYTES)
    app.state.buffer_folder = buffer_folder  # removed with the app
    return app
