"""Control messages: what people and tools ask a running service, and its answers.

- Requests (`impulse curriculum get|set|inspect`) are small JSON objects, since people type them: `{"set":
  ["replay_prob=0.8"]}`, `{"top": 10, "levels": true}`.
- Knob replies are JSON objects as well (`{"ok": ..., "knobs": ..., "changed": ...}`).
- An inspect reply is a CONTROL frame: a `report` (JSON) or an `error` in its meta, and optionally the arrays of
  the levels it lists.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.stamp import Stamp

REPORT = "report"
ERROR = "error"


def control_request(**fields: Any) -> bytes:
    """A request as its JSON bytes."""
    return json.dumps(fields).encode("utf-8")


def control_reply(payload: bytes) -> dict[str, Any]:
    """A control request's or reply's JSON object; ValueError with the reason if it is not one."""
    try:
        value = json.loads(payload.decode("utf-8"))
    except (ValueError, RecursionError) as err:  # also nesting deeper than the parser's recursion limit
        raise ValueError(f"not a JSON control message: {err}") from err
    if not isinstance(value, dict):
        raise ValueError(f"a control message is a JSON object, got {type(value).__name__}")
    return value


def encode_report(stamp: Stamp, report: Mapping[str, Any], arrays: Mapping[str, np.ndarray] | None = None,
                  ) -> bytearray:
    """An inspect reply: `report` (JSON-serialisable) and the arrays of what it lists."""
    return encode(Kind.CONTROL, arrays or {}, run=stamp.run, meta={REPORT: dict(report)})


def encode_refusal(stamp: Stamp, error: str) -> bytearray:
    """An inspect reply saying why there is no report."""
    return encode(Kind.CONTROL, {}, run=stamp.run, meta={ERROR: error})


class Report(NamedTuple):
    """A received inspect reply: the report, or the error the service gave instead, and the arrays."""

    report: dict[str, Any] | None
    error: str | None
    arrays: dict[str, np.ndarray]


def decode_report(payload: bytes, run: str) -> Report:
    """An inspect reply; raises `bus.codec.Rejected` for a malformed frame or one with neither a report (an
    object) nor an error (a string)."""
    message = decode(payload, run=run, kinds=Kind.CONTROL)
    report, error = message.meta.get(REPORT), message.meta.get(ERROR)
    if isinstance(error, str):
        return Report(None, error, message.arrays)
    if not isinstance(report, dict):
        raise Rejected("schema", "an inspect reply with neither a report nor an error")
    return Report(report, None, message.arrays)
