"""Fuzzing of every reader of a message that arrives from the network, one reader per message kind.

Whatever can reach the Zenoh router can publish on a run's keys, so every process reads hostile bytes: the learner
reads trajectories, an actor reads weights, acknowledgements and level batches, the curriculum reads level results
and control queries, the launcher reads status lines, `impulse curriculum inspect` reads CONTROL replies. Each
reader here is called exactly as its process calls it, and must either return a well-typed result or refuse the
input with its documented rejection: `bus.codec.Rejected` with a reason from REASONS (plus
`curriculum.wire.ResultsError` for impossible result counts, and ValueError for the JSON of control queries).
Any other exception would take a service down on one bad packet. A reader must also never allocate by a size a
frame merely declares: tracemalloc measures the peak allocation of every hostile read, and of a sample of the
others, against a bound proportional to the input (see `alloc_bound`).

Each reader gets CASES inputs from four families:
- random bytes;
- random bytes after a valid header prefix (half of them with table and body lengths that match the payload, so
  they reach the JSON table);
- mutations of valid frames made by the real encoder of that kind: bit flips, byte replacements, insertions,
  deletions, truncations, edits of the JSON table (lengths fixed up) and splices of two valid frames;
- valid frames with hostile tables, meta or contents: wrong types, huge, negative or non-finite numbers, huge
  declared shapes and lengths, other dtypes, other shapes, renamed, missing or extra arrays (another tree
  structure), NaN/Inf in float arrays, impossible counts.

Templates are tiny (2 environments, 2 steps, a 16-wide network) and built by shape evaluation, without compiling
the rollout or the network. Seeds are
fixed: a failure names the reader, the family and the case number, which reproduce it. `pytest -s` prints one line
per reader: cases, accepted, rejected by reason, and the largest allocation of one read.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
import tracemalloc
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from types import SimpleNamespace
from typing import Any

import jax
import numpy as np
import pytest

from impulse.actors.wire import (
    TRAJECTORY_FINITE,
    TrajectoryWire,
    checked_tree,
    trajectory_schema,
    trajectory_template,
    weights_hash,
    weights_schema,
)
from impulse.bus.codec import (
    ALIGN,
    DIGEST_SIZE,
    FLAG_DIGEST,
    HEADER,
    HEADER_SIZE,
    MAX_TABLE_BYTES,
    REASONS,
    TREE_HASH_META,
    WIRE_DTYPES,
    Header,
    Kind,
    Message,
    Rejected,
    decode,
    tree_hash,
)
from impulse.bus.control import Report, control_reply, control_request, decode_report, encode_refusal, encode_report
from impulse.bus.credits import Credit, decode_credit, encode_credit
from impulse.bus.evaluations import Evaluation, decode_evaluation, encode_evaluation
from impulse.bus.inbox import Received
from impulse.bus.keys import Keys
from impulse.bus.levels import decode_level_batch, decode_level_results, encode_level_batch, encode_level_results
from impulse.bus.routes import ROUTES
from impulse.bus.stamp import Stamp
from impulse.bus.status import Status, StatusPublisher, read_status
from impulse.bus.trajectories import decode_trajectory, encode_trajectory
from impulse.bus.weights import PUBLISHED_AT, decode_weights, encode_weights
from impulse.curriculum.results import LevelResults
from impulse.curriculum.wire import (
    ResultsError,
    level_batch_arrays,
    level_batch_from_message,
    level_batch_schema,
    level_batch_template,
    results_arrays,
    results_from_message,
)
from impulse.engine.env.spec import EnvSpec
from impulse.engine.levels.level import LEVEL_ID_WORDS
from impulse.engine.pytree import path_name, tree_arrays
from impulse.learner.agent import make_agent
from impulse.learner.config import NetworkConfig
from impulse.learner.service import LEARNER_ID

RUN = "fuzz-run"
CASES = 10_000
"""Inputs per reader."""
RESULT_ROWS = 8
"""Rows of the curriculum's result chunks (a valid frame of 12 results is split in two)."""
FAMILIES = ("random", "header_prefix", "mutation", "hostile")
FAMILY_SHARES = (0.15, 0.15, 0.55, 0.15)
NETWORK = NetworkConfig(kind="entity", width=16, depth=1, entity_encoder_size=16, entity_heads=2, entity_head_size=8)

ALLOC_FACTOR = 8
ALLOC_SLACK = 64 << 10
TRACE_EVERY = 50
"""Every hostile input is read under tracemalloc, and besides them every TRACE_EVERY-th input of the other families
(tracing makes a read about eight times slower, and the file must stay fast)."""


def alloc_bound(size: int) -> int:
    """The most one read of a `size`-byte input may allocate: ALLOC_FACTOR times the input, plus ALLOC_SLACK.

    A read legitimately allocates in proportion to what it was given: the table bytes and their decoded string
    (2x the table), the parsed JSON (a list, two strs and a few ints per array entry: about 4x the table text;
    a 5000-digit number or string costs about its length), one numpy view per array, the isfinite masks of the
    schema check (at most the body) and, for level results, the padded result chunks (about the body). 8x the
    input covers that with room to spare. The slack covers what does not scale with the input: the Rejected
    exception and its traceback, the error text, a JAX tree rebuild, a RecursionError unwinding a nested table.
    The valid inputs here are 0.2 to 10 kB, so a read may allocate well under a megabyte, while a frame that
    declares a 2**62-byte array or a 2**63-byte body would need gigabytes if any of it were allocated.
    """
    return ALLOC_FACTOR * size + ALLOC_SLACK


# ------------------------------------------------------------------------------------------------- frame layout


@cache
def parts(frame: bytes) -> tuple[Header, bytes, bytes]:
    """Header, table text and body of a valid frame (without its digest, if it has one)."""
    header = Header._make(HEADER.unpack_from(frame, 0))
    end = len(frame) - (DIGEST_SIZE if header.flags & FLAG_DIGEST else 0)
    return header, frame[HEADER_SIZE : HEADER_SIZE + header.table_len], frame[end - header.body_len : end]


def split(frame: bytes) -> tuple[Header, dict[str, Any], bytes]:
    """Header, parsed table (a fresh copy to modify) and body of a valid frame."""
    header, table, body = parts(frame)
    return header, json.loads(table), body


def assemble(header: Header, table: bytes, body: bytes | bytearray, **fields: int) -> bytes:
    """A frame of `table` and `body` whose header lengths match them, unless `fields` overrides header fields, with
    a correct digest where the header's flag asks for one: anyone can compute a digest, so hostile frames carry
    valid ones and reach the checks behind it."""
    header = header._replace(table_len=len(table), body_len=len(body))._replace(**fields)
    padding = bytes(-(HEADER_SIZE + len(table)) % ALIGN)
    frame = HEADER.pack(*header) + table + padding + bytes(body)
    if header.flags & FLAG_DIGEST:
        frame += hashlib.blake2b(frame, digest_size=DIGEST_SIZE).digest()
    return frame


def table_json(table: Any) -> bytes:
    return json.dumps(table, separators=(",", ":")).encode("utf-8")


# ------------------------------------------------------------------------------------------------ valid inputs


def random_like(template: Any, rng: np.random.Generator) -> Any:
    """A tree of host arrays shaped like `template`: finite floats, small non-negative ints, random bools."""

    def fill(leaf: Any) -> np.ndarray:
        dtype = np.dtype(leaf.dtype)
        if dtype.kind == "b":
            return rng.random(leaf.shape) < 0.3
        if np.issubdtype(dtype, np.integer):
            return rng.integers(1, 4, leaf.shape).astype(dtype)
        return rng.standard_normal(leaf.shape).astype(dtype)

    return jax.tree.map(fill, template)


def level_results(rng: np.random.Generator, count: int) -> LevelResults:
    """`count` valid results padded with two invalid rows (which `results_arrays` leaves out)."""
    rows = count + 2
    episodes = rng.integers(1, 5, rows).astype(np.int32)

    def floats() -> np.ndarray:
        return rng.standard_normal(rows).astype(np.float32)

    return LevelResults(
        level_id=rng.integers(1, 2**32, (rows, LEVEL_ID_WORDS), dtype=np.uint32),
        valid=np.arange(rows) < count,
        episodes=episodes,
        solved=(episodes * rng.random(rows)).astype(np.int32),
        return_sum=floats(),
        return_max=floats(),
        value_sum=floats(),
        pvl_sum=np.abs(floats()),
        l1_sum=np.abs(floats()),
        policy_version=rng.integers(0, 100, rows).astype(np.int32),
    )


def status_frames(statuses: list[tuple[str, dict[str, Any]]]) -> list[bytes]:
    """Status frames sent by the real `StatusPublisher`, through a stand-in bus that keeps what is put."""
    frames: list[bytes] = []
    sink = SimpleNamespace(put=lambda frame: frames.append(bytes(frame)))
    for role, status in statuses:
        bus = SimpleNamespace(keys=Keys(RUN), stamp=Stamp(RUN), role=role, ident="0",
                              publisher=lambda *_, **__: sink)
        StatusPublisher(bus, every_s=0.0).publish(status)
    return frames


# ------------------------------------------------------------------------------------------- result checking


def check_message(kind: Kind | None) -> Callable[[Message], None]:
    def check(message: Message) -> None:
        assert isinstance(message, Message)
        assert kind is None or message.kind is kind
        assert isinstance(message.meta, dict)
        for name, array in message.arrays.items():
            assert isinstance(name, str) and isinstance(array, np.ndarray) and not array.flags.writeable

    return check


def check_tree(template: Any, finite: Callable[[str], bool]) -> Callable[[Any], None]:
    """The result has the template's structure, dtypes and shapes, and the arrays `finite` names hold no NaN/Inf."""
    structure = jax.tree.structure(template)
    specs = jax.tree_util.tree_flatten_with_path(template)[0]

    def check(tree: Any) -> None:
        assert jax.tree.structure(tree) == structure
        for (path, spec), leaf in zip(specs, jax.tree.leaves(tree), strict=True):
            assert isinstance(leaf, np.ndarray) and leaf.shape == spec.shape and leaf.dtype == spec.dtype, path
            if finite(path_name(path)) and leaf.dtype.kind == "f":
                assert np.isfinite(leaf).all(), path

    return check


def check_results(chunks: list[LevelResults]) -> None:
    assert isinstance(chunks, list)
    for chunk in chunks:
        assert isinstance(chunk, LevelResults)
        assert all(np.shape(leaf)[0] == RESULT_ROWS for leaf in chunk)
        valid = np.asarray(chunk.valid)
        episodes, solved = np.asarray(chunk.episodes)[valid], np.asarray(chunk.solved)[valid]
        assert ((solved >= 0) & (solved <= episodes)).all()
        assert (np.asarray(chunk.level_id)[valid] != 0).any(axis=-1).all()
        for name in ("return_sum", "return_max", "value_sum", "pvl_sum", "l1_sum"):
            assert np.isfinite(getattr(chunk, name)).all(), name


def check_status(result: Status) -> None:
    assert result.role == "actor" and result.ident == "actor-0" and isinstance(result.status, dict)


def check_control(request: dict[str, Any]) -> None:
    assert isinstance(request, dict)


def check_evaluation(evaluation: Evaluation) -> None:
    assert type(evaluation.skipped) is int and evaluation.skipped >= 0
    assert all(0.0 <= scores["solve_rate"] <= 1.0 for scores in evaluation.levels.values())
    assert all(0.0 <= rate <= 1.0 for rate in evaluation.groups.values())


def check_credit(credit: Credit) -> None:
    assert all(type(value) is int for value in credit)


def check_report(reply: Report) -> None:
    assert (reply.report is None) != (reply.error is None)
    assert isinstance(reply.report, dict) or isinstance(reply.error, str)


# --------------------------------------------------------------------------------------------------- readers


@dataclass(frozen=True)
class Target:
    """One reader under test, with the valid inputs its mutations and hostile variants start from."""

    name: str
    frames: tuple[bytes, ...]
    """Valid inputs made by the real encoder of this kind; all must be accepted."""
    read: Callable[[bytes], Any]
    check: Callable[[Any], None]
    refusals: tuple[type[Exception], ...]
    """The documented rejections of this reader: anything else raised fails the test."""
    hostile_reasons: frozenset[str]
    """Reasons the hostile family must produce at least once (proof that the reader's checks were reached)."""
    others: tuple[bytes, ...] = ()
    """Valid frames of other kinds, spliced into this kind's frames."""
    is_frame: bool = True
    hostile_refused_share: float = 0.5
    """Least share of the hostile family refused: lower for readers without a schema, which accept any content."""
    decoder: str = ""
    """The decoder under test as the route table names it (`bus.routes.Route.decoder`); "" for the rest."""


def reason(error: Exception) -> str:
    if isinstance(error, Rejected):
        assert error.reason in REASONS, error
        assert error.detail, error
        return error.reason
    return type(error).__name__


@cache
def targets() -> dict[str, Target]:
    """Every reader of a received message, with valid inputs from the real encoders (built once)."""
    rng = np.random.default_rng(0)
    agent = make_agent(NETWORK, EnvSpec())

    traj_template = trajectory_template(EnvSpec(), num_envs=2, num_steps=2)
    traj_schema = trajectory_schema(traj_template)
    traj_max_bytes = 2 * sum(spec.dtype.itemsize * math.prod(spec.shape) for spec in traj_schema.arrays.values())
    traj_max_bytes += 1 << 20  # as the learner bounds its frames
    stamp = Stamp(RUN, epoch=1, policy_version=4)  # as each process's bus holds one
    # Both trajectory formats, as actors send them: padded (the default) and compact (with float16 features too).
    padded_wire = TrajectoryWire(traj_template, EnvSpec().sizes)
    compact_wire = TrajectoryWire(traj_template, EnvSpec().sizes, compact=True)

    def traj_frame(wire: TrajectoryWire, seq: int) -> bytearray:
        return encode_trajectory(stamp, wire.pack(tree_arrays(random_like(traj_template, rng))), seq=seq,
                                 incarnation=12345 + seq, actor_index=seq, layout=wire.format)

    padded_frames = [traj_frame(padded_wire, seq) for seq in (1, 2)]
    traj_frames = [traj_frame(compact_wire, 3),
                   traj_frame(TrajectoryWire(traj_template, EnvSpec().sizes, compact=True, float16=True), 4)]

    params_template = jax.eval_shape(agent.init, jax.random.PRNGKey(0))
    weights_frames = []
    for version in (3, 4):
        params = random_like(params_template, rng)
        weights_frames.append(encode_weights(Stamp(RUN, epoch=1, policy_version=version), tree_arrays(params),
                                             weights_hash(params)))

    credit_frames = [encode_credit(stamp, 12345, seq) for seq in (3, 2**40)]  # as the learner acknowledges

    results_frames = [encode_level_results(stamp, results_arrays(level_results(rng, count)), seq=7)
                      for count in (5, RESULT_ROWS + 4)]

    levels_template = level_batch_template(EnvSpec().sizes, 2)
    levels_schema = level_batch_schema(levels_template)
    levels_frames = [encode_level_batch(stamp, level_batch_arrays(random_like(levels_template, rng)))
                     for _ in (1, 2)]

    evaluation_frames = [
        encode_evaluation(stamp, {"s/h0_weak_thrust": {"solve_rate": 0.5, "mean_return": 0.1, "mean_length": 40.0},
                                  "s_easy_car_right": {"solve_rate": 1.0, "mean_return": 0.9, "mean_length": 12.5}},
                          {"s_all": 0.5, "s_h": 0.5}, skipped=2),
        encode_evaluation(stamp, {}, {}),
    ]
    metrics_frames = status_frames([
        ("learner", {"role": "learner", "name": LEARNER_ID, "epoch": 1, "policy_version": 4, "update": 10,
                     "num_updates": 100, "updates_per_s": 2.5, "rejected": {"bad_size": 1}, "solve_rate": None}),
        ("actor", {"role": "actor", "name": "actor-0", "steps_per_s": 1e4, "policy_version": 4, "lag": 1,
                   "in_flight": 2, "levels": "random", "monitor": None}),
    ])

    report = {"method": "plr", "knobs": {"replay_prob": 0.5}, "summary": {"buffer_fill": 0.25},
              "top": [{"level_id": 17, "score": 0.5}], "lineage": []}
    control_frames = [encode_report(stamp, report, tree_arrays(random_like(levels_template.levels, rng))),
                      encode_refusal(stamp, "top must be an integer")]
    control_queries = [control_request(top=3, levels=True), control_request(set=["replay_prob=0.8"]),
                       control_request()]

    frames = {
        Kind.TRAJECTORY: traj_frames,
        Kind.WEIGHTS: weights_frames,
        Kind.CREDIT: credit_frames,
        Kind.LEVEL_RESULTS: results_frames,
        Kind.LEVELS: levels_frames,
        Kind.METRICS: metrics_frames,
        Kind.CONTROL: control_frames,
        Kind.EVALUATION: evaluation_frames,
    }
    assert set(frames) == set(Kind), "a message kind without a fuzzed reader"
    every = tuple(bytes(frame) for kind_frames in frames.values() for frame in kind_frames)

    def others(kind: Kind) -> tuple[bytes, ...]:
        return tuple(bytes(frame) for other, kind_frames in frames.items() if other != kind for frame in kind_frames)

    framing = frozenset({"bad_table", "bad_dtype", "bad_shape", "bad_size", "truncated", "wrong_kind", "bad_version",
                         "wrong_run"})
    content = framing | {"schema", "non_finite"}

    def target(name: str, kind: Kind, decoder: str, read: Callable[[bytes], Any], check: Callable[[Any], None],
               reasons: frozenset[str], refusals: tuple[type[Exception], ...] = (Rejected,),
               refused_share: float = 0.5) -> Target:
        return Target(name, tuple(bytes(frame) for frame in frames[kind]), read, check, refusals, reasons,
                      others(kind), hostile_refused_share=refused_share, decoder=decoder)

    listed = [
        target("trajectory", Kind.TRAJECTORY, "bus.trajectories.decode_trajectory",
               lambda data: compact_wire.checked(decode_trajectory(data, RUN, traj_max_bytes,
                                                                   compact_wire.format).message),
               check_tree(traj_template, lambda name: any(name == f or name.startswith(f + "/")
                                                          for f in TRAJECTORY_FINITE)),
               content),
        Target("trajectory_padded", tuple(bytes(frame) for frame in padded_frames),
               lambda data: padded_wire.checked(decode_trajectory(data, RUN, traj_max_bytes,
                                                                  padded_wire.format).message),
               check_tree(traj_template, lambda name: any(name == f or name.startswith(f + "/")
                                                          for f in TRAJECTORY_FINITE)),
               (Rejected,), content, others(Kind.TRAJECTORY), decoder="bus.trajectories.decode_trajectory"),
        target("weights", Kind.WEIGHTS, "bus.weights.decode_weights",
               lambda data: checked_tree(decode_weights(data, RUN).message, weights_schema(params_template),
                                         params_template),
               check_tree(params_template, lambda path: True),
               content | {"tree_hash"}),
        target("credit", Kind.CREDIT, "bus.credits.decode_credit", lambda data: decode_credit(data, RUN), check_credit,
               framing | {"schema"}, refused_share=0.3),
        target("level_results", Kind.LEVEL_RESULTS, "bus.levels.decode_level_results",
               lambda data: results_from_message(decode_level_results(data, RUN), RESULT_ROWS),
               check_results, content | {"ResultsError"}, (Rejected, ResultsError)),
        target("levels", Kind.LEVELS, "bus.levels.decode_level_batch",
               lambda data: level_batch_from_message(decode_level_batch(data, RUN), levels_schema, levels_template),
               check_tree(levels_template, lambda path: True), content),
        target("metrics", Kind.METRICS, "bus.status.read_status",
               lambda data: read_status(Received(key=Keys(RUN).status("actor", "actor-0"), payload=data,
                                                 attachment=None), Keys(RUN)),
               check_status, framing | {"schema"}, refused_share=0.3),
        target("evaluation", Kind.EVALUATION, "bus.evaluations.decode_evaluation",
               lambda data: decode_evaluation(data, RUN), check_evaluation, framing | {"schema"}, refused_share=0.3),
        target("control", Kind.CONTROL, "bus.control.decode_report", lambda data: decode_report(data, RUN),
               check_report, framing, refused_share=0.3),
        Target("any_frame", every, lambda data: decode(data, run=RUN), check_message(None), (Rejected,),
               framing - {"wrong_kind"}, hostile_refused_share=0.3),
        Target("control_query", tuple(control_queries), control_reply, check_control, (ValueError,),
               frozenset({"ValueError"}), is_frame=False, hostile_refused_share=0.3),
    ]
    return {t.name: t for t in listed}


# ------------------------------------------------------------------------------------- input families: bytes

JSON_CHARS = b'0123456789-+.eE[]{}",:ntrufalsNIy \\'
"""Characters that change the meaning of a JSON table when written into it."""


def choose(rng: np.random.Generator, options: Any) -> Any:
    return options[int(rng.integers(len(options)))]


def random_input(rng: np.random.Generator, target: Target) -> bytes:
    longest = max(len(frame) for frame in target.frames)
    return rng.bytes(int(rng.integers(0, 2 * longest)))


def header_prefix_input(rng: np.random.Generator, target: Target) -> bytes:
    frame = choose(rng, target.frames)
    if not target.is_frame:  # a valid JSON opening, then noise
        return frame[: int(rng.integers(1, len(frame)))] + rng.bytes(int(rng.integers(0, 64)))
    header, _, body = parts(frame)
    if rng.random() < 0.5:
        prefix = frame[: int(rng.integers(4, HEADER_SIZE + header.table_len + 1))]
        return prefix + rng.bytes(int(rng.integers(0, len(frame))))
    # Lengths that match: the random table reaches the JSON parser, the random body the table's entries.
    table = bytes(choose(rng, JSON_CHARS) for _ in range(int(rng.integers(0, 48))))
    if rng.random() < 0.5:
        table = rng.bytes(int(rng.integers(0, 256)))
    return assemble(header, table, rng.bytes(int(rng.integers(0, len(body) + 1))))


def mutation_input(rng: np.random.Generator, target: Target) -> bytes:
    frame = choose(rng, target.frames)
    data = bytearray(frame)
    table_end = HEADER_SIZE + parts(frame)[0].table_len if target.is_frame else len(frame)
    # Two thirds land in the header and table, where a changed byte can change the meaning of the rest.
    position = int(rng.integers(0, table_end if rng.random() < 2 / 3 else len(data)))
    op = int(rng.integers(8))
    if op == 0:  # bit flips
        for _ in range(int(rng.integers(1, 5))):
            spot = int(rng.integers(0, len(data))) if _ else position
            data[spot] ^= 1 << int(rng.integers(8))
    elif op == 1:  # replaced bytes
        for spot in rng.integers(0, len(data), int(rng.integers(1, 5))):
            data[int(spot)] = int(rng.integers(256))
        data[position] = int(rng.integers(256))
    elif op == 2:  # insertion
        data[position:position] = rng.bytes(int(rng.integers(1, 17)))
    elif op == 3:  # deletion
        del data[position : position + int(rng.integers(1, 17))]
    elif op == 4:  # truncation
        del data[int(rng.integers(0, len(data))) :]
    elif op == 5:  # JSON characters written into the table
        for _ in range(int(rng.integers(1, 4))):
            spot = int(rng.integers(HEADER_SIZE if target.is_frame else 0, table_end))
            data[spot] = choose(rng, JSON_CHARS)
    elif op == 6 and target.is_frame:  # table bytes inserted or deleted, lengths fixed up to match
        header, table_text, body = parts(frame)
        table = bytearray(table_text)
        spot = int(rng.integers(0, len(table)))
        if rng.random() < 0.5:
            table[spot:spot] = bytes(choose(rng, JSON_CHARS) for _ in range(int(rng.integers(1, 5))))
        else:
            del table[spot : spot + int(rng.integers(1, 5))]
        return assemble(header, bytes(table), body)
    else:  # splice: the start of one valid frame, the end of another (of this kind, or now and then another)
        pool = target.others if target.others and rng.random() < 0.25 else target.frames
        other = choose(rng, pool)
        return bytes(frame[: int(rng.integers(0, len(frame) + 1))] + other[int(rng.integers(0, len(other) + 1)) :])
    return bytes(data)


# --------------------------------------------------------------------------------- input families: hostile

NAN, INF = float("nan"), float("inf")
HOSTILE_NUMBERS = (-1, -(2**63), 0, 1, 7, 2**31, 2**32, 2**62, 2**63, 2**64, 10**4299, 1.5, -0.0, 1e308, NAN, INF,
                   -INF, True, False)
HOSTILE_VALUES = (*HOSTILE_NUMBERS, None, "", "x", "<f4", "9" * 5000, [], [1], [[2, 3]], {}, {"a": [1]})
HUGE_SHAPES = ([2**31, 2**31], [2**62], [0, 2**62], [2**20] * 3, [2**63], [1] * 33, [10**4299], [2**32, 0, 2**40],
               [2**16] * 4, [3, -1], [2**22], [1024, 1024, 4], [2**26])
"""Declared shapes far beyond any payload here: astronomical ones (allocating them would fail outright) and ones
of 4 to 256 MB, which would succeed, so that only the allocation bound can tell they were allocated."""
SAME_SIZE_DTYPES = {1: ("|b1", "|u1", "|i1"), 2: ("<f2", "<i2", "<u2"), 4: ("<f4", "<i4", "<u4"),
                    8: ("<f8", "<i8", "<u8")}
FOREIGN_DTYPES = (">f4", "<c8", "|O", "<U4", "float32", "<V8", "<f4 ", "", "<M8")
META_KEYS = (TREE_HASH_META, PUBLISHED_AT, "incarnation", "acked_seq", "actor", "report", "error", "name", "role",
             "policy_version", "rejected")
RAW_TABLES = (
    b"[" * 5000 + b"]" * 5000,
    b'{"arrays": ' + b"[" * 3000 + b"]" * 3000 + b"}",
    b'{"arrays": [], "meta": {"x": ' + b"9" * 5000 + b"}}",
    b'{"arrays": [["a", "<f4", [' + b"9" * 4301 + b"], 0, 4]]}",
    b'{"arrays": [["a", "<f4", [NaN], Infinity, -Infinity]]}',
    b'{"arrays": [], "arrays": {}}',
    b'{"arrays": [], "meta": {"tree_hash": NaN}, "sender": "\xff\xfe"}',
    b'{"arrays": [["a", "<f4", [1e400], 0, 4]]}',
    b"null",
    b'"arrays"',
    b"",
    b"\x00" * 64,
)


def _entry(table: dict[str, Any], rng: np.random.Generator) -> list[Any]:
    """One entry of the array table, to be modified (a new, empty one in a table without arrays)."""
    entries = table["arrays"]
    if not entries:
        entries.append(["extra", "<f4", [0], 0, 0])
    return entries[int(rng.integers(len(entries)))]


def _hostile_entry_field(rng, header, table, body):
    if rng.random() < 0.1:
        table["arrays"].append(choose(rng, HOSTILE_VALUES))
    else:
        _entry(table, rng)[int(rng.integers(5))] = choose(rng, HOSTILE_VALUES)
    return assemble(header, table_json(table), body)


def _hostile_huge_declaration(rng, header, table, body):
    """An array (or the header) that declares a size far beyond the payload."""
    if rng.random() < 0.3:
        if rng.random() < 0.5:
            return assemble(header, table_json(table), body, table_len=choose(rng, [2**32 - 1, MAX_TABLE_BYTES + 1]))
        return assemble(header, table_json(table), body, body_len=choose(rng, [2**40, 2**62, 2**63, 2**64 - 1]))
    entry = _entry(table, rng)
    shape = list(choose(rng, HUGE_SHAPES))
    entry[2] = shape
    itemsize = WIRE_DTYPES[entry[1]].itemsize
    entry[4] = math.prod(shape) * itemsize if rng.random() < 0.7 else choose(rng, HOSTILE_NUMBERS)
    entry[3] = int(choose(rng, [0, entry[3], len(body), 2**62]))
    return assemble(header, table_json(table), body)


def _hostile_dtype(rng, header, table, body):
    entry = _entry(table, rng)
    itemsize = WIRE_DTYPES[entry[1]].itemsize
    roll = rng.random()
    if roll < 0.5:  # same size: the frame stays well formed, only the receiver's schema can tell
        entry[1] = choose(rng, [d for d in SAME_SIZE_DTYPES[itemsize] if d != entry[1]])
    elif roll < 0.8:  # another size, nbytes declared to match (the array then fits inside its old place or not)
        entry[1] = choose(rng, list(WIRE_DTYPES))
        entry[4] = math.prod(entry[2]) * WIRE_DTYPES[entry[1]].itemsize
    else:
        entry[1] = choose(rng, FOREIGN_DTYPES)
    return assemble(header, table_json(table), body)


def _hostile_shape(rng, header, table, body):
    """Another shape that the body can hold: the frame decodes, the schema must refuse it."""
    entry = _entry(table, rng)
    shape = entry[2]
    count = math.prod(shape)
    options = [[count], [1, *shape], shape[::-1], [*shape, 1], [max(count - 1, 0)]]
    if shape:
        options.append([*shape[:-1], max(shape[-1] - 1, 0)])
    entry[2] = choose(rng, options)
    entry[4] = math.prod(entry[2]) * WIRE_DTYPES[entry[1]].itemsize
    return assemble(header, table_json(table), body)


def _hostile_structure(rng, header, table, body):
    """Another tree: an array missing, renamed, moved under or over its parent, or an extra one."""
    entries = table["arrays"]
    if not entries:
        entries.append(["extra", "<f4", [0], 0, 0])
        return assemble(header, table_json(table), body)
    index = int(rng.integers(len(entries)))
    name = entries[index][0]
    roll = int(rng.integers(5))
    if roll == 0:
        del entries[index]
    elif roll == 1:
        entries[index][0] = name + "_renamed"
    elif roll == 2:
        entries[index][0] = name.rsplit("/", 1)[0] if "/" in name else name + "/leaf"
    elif roll == 3:
        entries.append([name + "/extra", *entries[index][1:]])
    else:
        entries.append(list(entries[index]))  # the same name twice
    meta = table.get("meta", {})
    if TREE_HASH_META in meta and rng.random() < 0.5:  # a sender honest about its foreign structure
        unique = {e[0]: np.zeros(e[2], WIRE_DTYPES[e[1]]) for e in entries}
        meta[TREE_HASH_META] = tree_hash(unique)
    return assemble(header, table_json(table), body)


def _hostile_meta(rng, header, table, body):
    roll = rng.random()
    if roll < 0.15:
        table["meta"] = choose(rng, HOSTILE_VALUES)
    elif roll < 0.3:
        table["sender"] = choose(rng, HOSTILE_VALUES)
    elif roll < 0.4:
        table.pop(choose(rng, ["meta", "sender", "arrays"]), None)
    else:
        meta = table.setdefault("meta", {})
        key = choose(rng, META_KEYS + tuple(meta))
        if rng.random() < 0.2:
            meta.pop(key, None)
        else:
            meta[key] = choose(rng, HOSTILE_VALUES)
    return assemble(header, table_json(table), body)


def _hostile_values(rng, header, table, body):
    """NaN/Inf in a float array, or extreme values in an integer array (negative counts, zero level ids)."""
    entries = [e for e in table["arrays"] if e[4] > 0]
    if not entries:
        return _hostile_meta(rng, header, table, body)
    _, dtype_str, _, offset, nbytes = choose(rng, entries)
    dtype = WIRE_DTYPES[dtype_str]
    values = np.frombuffer(body, dtype, count=nbytes // dtype.itemsize, offset=offset).copy()
    spots = rng.integers(0, values.size, int(rng.integers(1, 4)))
    if dtype.kind == "f":
        values[spots] = choose(rng, [NAN, INF, -INF])
    elif dtype.kind in "iu":
        info = np.iinfo(dtype)
        values[spots] = choose(rng, [0, info.min, info.max, -1 if dtype.kind == "i" else 0])
    else:
        values[spots] = ~values[spots]
    body = bytearray(body)
    body[offset : offset + nbytes] = values.tobytes()
    return assemble(header, table_json(table), body)


def _hostile_header(rng, header, table, body):
    field, value = choose(rng, [
        ("table_len", header.table_len + int(rng.integers(-64, 65))),
        ("body_len", header.body_len + int(rng.integers(-64, 65))),
        ("kind", int(rng.integers(0, 10))),
        ("schema_version", int(rng.integers(0, 4))),
        ("run_hash", int(rng.integers(0, 2**63))),
        ("flags", int(rng.integers(0, 2**32))),
        ("policy_version", 2**64 - 1),
        ("learner_epoch", 2**32 - 1),
    ])
    return assemble(header, table_json(table), body, **{field: max(value, 0)})


def _hostile_raw_table(rng, header, table, body):
    return assemble(header, choose(rng, RAW_TABLES), body)


HOSTILE_FRAME_OPS = (_hostile_entry_field, _hostile_huge_declaration, _hostile_dtype, _hostile_shape,
                     _hostile_structure, _hostile_meta, _hostile_values, _hostile_values, _hostile_header,
                     _hostile_raw_table)

HOSTILE_QUERIES = (
    {"top": INF}, {"top": NAN}, {"top": -INF}, {"top": 10**4299}, {"top": -(2**63)}, {"top": "ten"}, {"top": [3]},
    {"top": None}, {"levels": "yes"}, {"set": "replay_prob=0.8"}, {"set": [1, 2]}, {"set": {"replay_prob": INF}},
    {"set": ["replay_prob=nan"]}, [], [1, 2], "top", 3, None, 1e308,
)
RAW_QUERIES = (b"[" * 100_000, b'{"top": ' + b"9" * 5000 + b"}", b'{"top": 1e400}', b'{"top": -1e999}',
               b'{"top": Infinity}', b'{"a": NaN}', b"\xff\xfe{}", b"", b"{", b'{"top": 3', b"{}" * 3,
               b'{"x": "' + b"\\ud800" + b'"}', b"\x00")


def hostile_input(rng: np.random.Generator, target: Target) -> bytes:
    if not target.is_frame:
        if rng.random() < 0.5:
            return choose(rng, RAW_QUERIES)
        return json.dumps(choose(rng, HOSTILE_QUERIES)).encode("utf-8")
    header, table, body = split(choose(rng, target.frames))
    return choose(rng, HOSTILE_FRAME_OPS)(rng, header, table, body)


GENERATORS = {"random": random_input, "header_prefix": header_prefix_input, "mutation": mutation_input,
              "hostile": hostile_input}


# ------------------------------------------------------------------------------------------------------ fuzz


@dataclass
class Tally:
    """What one reader made of its inputs."""

    cases: int = 0
    accepted: Counter[str] = field(default_factory=Counter)  # family -> accepted inputs
    refused: Counter[str] = field(default_factory=Counter)  # family -> refused inputs
    reasons: Counter[str] = field(default_factory=Counter)  # reason -> refused inputs
    hostile_reasons: set[str] = field(default_factory=set)  # reasons seen in the hostile family
    traced: int = 0  # reads measured by tracemalloc
    peak: int = 0  # largest allocation of one read, bytes
    peak_case: str = ""
    over_bound: list[str] = field(default_factory=list)  # reads that allocated more than alloc_bound allows


def read_one(target: Target, data: bytes, case: str) -> tuple[Any, Exception | None]:
    """The reader's result or documented rejection; any other exception fails the test, naming the case."""
    try:
        return target.read(data), None
    except target.refusals as refusal:
        return None, refusal
    except Exception as other:  # the property under test: nothing else may escape a reader
        pytest.fail(f"{target.name}: {case} raised {type(other).__name__}: {other}; input ({len(data)} bytes) "
                    f"starts {data[:160]!r}")


def fuzz(target: Target, rng: np.random.Generator, cases: int) -> Tally:
    """Feed `cases` generated inputs to the reader; hostile ones (and a sample of the rest) under tracemalloc."""
    tally = Tally()
    families = rng.choice(len(FAMILIES), size=cases, p=FAMILY_SHARES)
    for case, family_index in enumerate(families):
        family = FAMILIES[family_index]
        data = GENERATORS[family](rng, target)
        label = f"case {case} ({family}, {len(data)} bytes)"
        if family == "hostile" or case % TRACE_EVERY == 0:
            tracemalloc.start()  # a fresh start per read: the peak is what this read allocated
            try:
                result, error = read_one(target, data, label)
                peak = tracemalloc.get_traced_memory()[1]
            finally:
                tracemalloc.stop()
            tally.traced += 1
            if peak > tally.peak:
                tally.peak, tally.peak_case = peak, label
            if peak > alloc_bound(len(data)):
                tally.over_bound.append(f"{label}: {peak} B")
        else:
            result, error = read_one(target, data, label)
        tally.cases += 1
        if error is None:
            target.check(result)
            tally.accepted[family] += 1
        else:
            why = reason(error)
            tally.refused[family] += 1
            tally.reasons[why] += 1
            if family == "hostile":
                tally.hostile_reasons.add(why)
    return tally


FRAME_READERS = ("trajectory", "weights", "credit", "level_results", "levels", "metrics", "evaluation", "control",
                 "any_frame")


def test_every_route_has_a_fuzzed_decoder() -> None:
    """Each message family of the route table is read by a decoder this file fuzzes (liveliness carries nothing)."""
    fuzzed = {target.decoder for target in targets().values()} - {""}
    routed = {route.decoder for route in ROUTES if route.decoder is not None}
    assert routed - fuzzed == set(), "routes whose decoder is not fuzzed"
    assert fuzzed - routed == set(), "fuzzed decoders no route names"
    for name in routed:  # the names resolve to the functions
        module, function = name.rsplit(".", 1)
        assert callable(getattr(importlib.import_module(f"impulse.{module}"), function)), name


@pytest.mark.parametrize("name", [*FRAME_READERS, "control_query"])
def test_reader_returns_a_typed_result_or_a_documented_rejection(name: str) -> None:
    target = targets()[name]
    for frame in target.frames:  # the valid inputs themselves are accepted: a reader that refuses all would pass
        target.check(target.read(frame))
    if target.is_frame:
        for frame in target.frames:
            _, table, body = split(frame)
            message = decode(frame, run=RUN)
            for array_name, dtype, shape, offset, _ in table["arrays"]:
                expected = np.frombuffer(body, WIRE_DTYPES[dtype], count=math.prod(shape), offset=offset)
                np.testing.assert_array_equal(message.arrays[array_name].ravel(), expected)

    seed = sum(name.encode())  # one fixed seed per reader
    tally = fuzz(target, np.random.default_rng(seed), CASES)
    accepted = sum(tally.accepted.values())
    mutated = tally.accepted["mutation"] + tally.refused["mutation"]
    hostile = tally.accepted["hostile"] + tally.refused["hostile"]
    print(f"\n{name}: {tally.cases} cases, {accepted} accepted, {tally.cases - accepted} rejected "
          f"{dict(tally.reasons.most_common())}; refused {tally.refused['mutation']}/{mutated} mutated, "
          f"{tally.refused['hostile']}/{hostile} hostile; {tally.traced} reads traced, the largest allocated "
          f"{tally.peak} B ({tally.peak_case})")

    assert tally.cases == CASES
    assert not tally.over_bound, f"{name}: reads allocated more than {ALLOC_FACTOR}x their input + " \
                                 f"{ALLOC_SLACK} B: {tally.over_bound[:5]}"
    assert tally.accepted["random"] == 0 or not target.is_frame, "random bytes were accepted as a frame"
    assert tally.refused["mutation"] >= 0.5 * mutated, f"{name}: only {tally.refused['mutation']} of {mutated} refused"
    assert tally.accepted["mutation"] > 0, f"{name}: no mutated input was accepted, so the mutations all broke framing"
    share = target.hostile_refused_share
    assert tally.refused["hostile"] >= share * hostile, f"{name}: only {tally.refused['hostile']} of {hostile} refused"
    missing = target.hostile_reasons - tally.hostile_reasons
    assert not missing, f"{name}: hostile inputs never produced {sorted(missing)}; got {sorted(tally.hostile_reasons)}"


@pytest.mark.parametrize("name", FRAME_READERS)
def test_frames_declaring_huge_sizes_are_refused_without_allocating(name: str) -> None:
    """The largest valid frame of the kind, with huge table and body lengths in its header, and with its first,
    middle and last arrays declaring each of HUGE_SHAPES (nbytes to match): every read stays within the allocation
    bound, and only an array of zero elements (which needs no memory whatever its other dimensions) gets through
    the frame decoder."""
    target = targets()[name]
    header, table_text, body = parts(max(target.frames, key=len))
    inputs = [(assemble(header, table_text, body, table_len=n), True) for n in (2**32 - 1, MAX_TABLE_BYTES + 1)]
    inputs += [(assemble(header, table_text, body, body_len=n), True) for n in (2**40, 2**62, 2**63, 2**64 - 1)]
    count = len(json.loads(table_text)["arrays"])
    for index in sorted({0, count // 2, max(count - 1, 0)}):
        for shape in HUGE_SHAPES:
            table = json.loads(table_text)
            entry = _entry(table, np.random.default_rng(index)) if not count else table["arrays"][index]
            entry[2], entry[4] = shape, math.prod(shape) * WIRE_DTYPES[entry[1]].itemsize
            inputs.append((assemble(header, table_json(table), body), math.prod(shape) != 0))
    for number, (data, must_refuse) in enumerate(inputs):
        tracemalloc.start()
        try:
            result, error = read_one(target, data, f"huge declaration {number}")
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak <= alloc_bound(len(data)), f"{name}: huge declaration {number} allocated {peak} B"
        if error is None:
            assert not must_refuse, f"{name}: huge declaration {number} was accepted"
            target.check(result)
