"""A real curriculum service in the test's own process, over a real bus: the small PLR service the curriculum
service tests drive cycle by cycle, and `serving`, which cycles it on a thread while a browser or a client talks
to it."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from impulse.bus.session import Bus
from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods import make_curriculum
from impulse.curriculum.service import CurriculumService
from impulse.deploy.config import ConfigError, apply_overrides
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.learner.checkpoint import CURRICULUM, Checkpointer

BATCH = 8
SPEC = EnvSpec()


def resolve_knobs(current, assignments):
    """What `impulse curriculum serve` checks a live knob change with: the config's own override rules."""
    try:
        return apply_overrides(current, assignments, source="live knob change")
    except ConfigError as err:
        raise ValueError(str(err)) from None


def start_service(bus: Bus, directory: Path, resume: bool) -> tuple[CurriculumService, Checkpointer]:
    """A PLR service of 16 levels on `bus`, checkpointing into `directory`, started (compiled) and ready."""
    config = CurriculumConfig(method="plr", buffer_size=16, noop_filter=False, replay_prob=0.0)
    checkpoints = Checkpointer(directory)
    service = CurriculumService(make_curriculum(config, SPEC, EnvParams(), BATCH), bus, checkpoints, "", resolve_knobs,
                                item=CURRICULUM, resume=resume)
    # As the run loop does in `impulse curriculum serve`: a cold compile on a loaded machine outlasts a query.
    service.start()
    return service, checkpoints


@contextlib.contextmanager
def serving(bus: Bus, directory: Path) -> Iterator[CurriculumService]:
    """A started service, cycled on a thread of its own until the block ends."""
    service, checkpoints = start_service(bus, directory, resume=False)
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            service.cycle()
            time.sleep(0.002)

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        yield service
    finally:
        stop.set()
        thread.join(timeout=10)
        checkpoints.close()
