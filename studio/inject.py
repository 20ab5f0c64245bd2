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
from impulse.curriculum.client import CurriculumClient, CurriculumUnreachable

LevelSender = Callable[[dict[str, Any]], dict[str, Any]]
"""Sends a Kinetix level-file object to the run's curriculum; its reply (`{"ok": true, "slot", "level_id",
"evicted"}` or `{"ok": false, "error"}`)."""

ANSWER_TIMEOUT_S = 15.0


def curriculum_sender(bus: BusConfig, run: str, timeout_s: float = ANSWER_TIMEOUT_S) -> LevelSender:
    """A `LevelSender` for the curriculum service of run `run` on `bus`: each call opens a short operator session
    (`curriculum.client`), asks once and closes it, so that a run that stops or restarts between two sends is
    found again."""

    def send(document: dict[str, Any]) -> dict[str, Any]:
        try:
            with CurriculumClient(bus, run, f"studio-{os.getpid()}", timeout_s) as client:
                return client.inject(document)
        except CurriculumUnreachable as err:
            return {"ok": False, "error": str(err)}

    return send
