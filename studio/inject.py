"""Sending an edited level into a running curriculum: the studio's side of the curriculum service's
`curriculum/inject` request (`curriculum.service`), asked over the run's bus as the operator role (the only role a
router lets ask it).

`impulse studio --run RUN_DIR` builds the sender from the run's configuration (`deploy.commands.studio`), since
the studio cannot read run configurations itself; `studio.app` serves it as `POST /api/inject`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

from impulse.bus.config import BusConfig
from impulse.bus.control import control_reply, control_request
from impulse.bus.keys import OPERATOR
from impulse.bus.session import Bus

LevelSender = Callable[[dict[str, Any]], dict[str, Any]]
"""Sends a Kinetix level-file object to the run's curriculum; its reply (`{"ok": true, "slot", "level_id",
"evicted"}` or `{"ok": false, "error"}`)."""

ANSWER_TIMEOUT_S = 15.0


def curriculum_sender(bus: BusConfig, run: str, timeout_s: float = ANSWER_TIMEOUT_S) -> LevelSender:
    """A `LevelSender` for the curriculum service of run `run` on `bus`: each call opens a short operator session,
    asks once and closes it, so that a run that stops or restarts between two sends is found again."""

    def send(document: dict[str, Any]) -> dict[str, Any]:
        with Bus(bus, run, OPERATOR, f"studio-{os.getpid()}") as session:
            key = session.keys.curriculum_inject
            if not session.wait_queryable(key, timeout_s):
                return {"ok": False, "error": f"no curriculum service of run {run!r} answers on {key} (is the run "
                                              "going, with env.levels=random?)"}
            replies = session.get(key, payload=control_request(level=document), timeout_s=timeout_s)
        if not replies:
            return {"ok": False, "error": f"the curriculum service of run {run!r} did not answer in {timeout_s:.0f} s"}
        try:
            return control_reply(replies[0])
        except ValueError as err:
            return {"ok": False, "error": f"unreadable answer from the curriculum service: {err}"}

    return send
