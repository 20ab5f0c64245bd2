"""Log formats: JSON lines a machine can parse, text lines a person can read, both carrying extra fields."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Iterator

import pytest

from impulse.deploy.runtime.log_setup import configure_logging


@pytest.fixture(autouse=True)
def restore_root_logger() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def test_json_lines_parse_with_extras() -> None:
    stream = io.StringIO()
    configure_logging("json", "info", stream=stream)
    log = logging.getLogger("impulse.test")
    log.info("update %d done", 7, extra={"sps": 1234.5, "run": "r1", "shape": (2, 3)})
    log.debug("hidden at info level")
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        log.exception("failed")
    lines = stream.getvalue().splitlines()
    first = json.loads(lines[0])
    assert first["level"] == "INFO" and first["logger"] == "impulse.test"
    assert first["msg"] == "update 7 done"
    assert first["sps"] == 1234.5 and first["run"] == "r1" and first["shape"] == [2, 3]
    assert first["ts"].endswith("Z") and "T" in first["ts"]
    assert len(lines) >= 2
    error = json.loads(stream.getvalue().split("\n", 1)[1])  # the traceback is escaped inside one line
    assert error["level"] == "ERROR" and "RuntimeError: boom" in error["exc"]


def test_text_format_shows_level_logger_message_and_extras() -> None:
    stream = io.StringIO()
    configure_logging("text", "debug", stream=stream)
    logging.getLogger("impulse.cli").debug("resolved", extra={"run_dir": "runs/a b", "seed": 3})
    line = stream.getvalue().strip()
    assert " DEBUG   impulse.cli: resolved " in line
    assert line.endswith("run_dir='runs/a b' seed=3")


def test_reconfiguring_replaces_the_handler() -> None:
    first, second = io.StringIO(), io.StringIO()
    configure_logging("text", "info", stream=first)
    configure_logging("json", "warning", stream=second)
    logging.getLogger("x").info("dropped")
    logging.getLogger("x").warning("kept")
    assert first.getvalue() == ""
    assert [json.loads(line)["msg"] for line in second.getvalue().splitlines()] == ["kept"]


def test_bad_level_is_rejected() -> None:
    with pytest.raises(ValueError, match="log level"):
        configure_logging("text", "loud")
