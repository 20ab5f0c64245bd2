"""Status lines as received: who sent one is read from its key, and `DropTotals` sums other processes' drop
counters over their restarts without counting a live process twice."""

from __future__ import annotations

import pytest

from impulse.bus.codec import Kind, Rejected, encode
from impulse.bus.inbox import Received
from impulse.bus.keys import Keys
from impulse.bus.status import DropTotals, Status, read_status

RUN = "status-run"
KEYS = Keys(RUN)


def received(key: str, status: dict) -> Received:
    return Received(key=key, payload=bytes(encode(Kind.METRICS, {}, run=RUN, meta=status)), attachment=None)


def test_the_sender_is_the_key_not_the_name_a_status_gives_itself() -> None:
    heard = read_status(received(KEYS.status("actor", "actor-3"), {"name": "learner", "finished": True}), KEYS)
    assert (heard.role, heard.ident) == ("actor", "actor-3")
    with pytest.raises(Rejected) as info:
        read_status(received(KEYS.traj("actor-3"), {"name": "learner"}), KEYS)
    assert info.value.reason == "schema" and "not a status key" in info.value.detail


def test_drop_totals_sum_incarnations_and_survive_a_restart() -> None:
    totals = DropTotals()
    totals.note(Status("actor", "actor-0", {"incarnation": 1, "written_off": 3, "rejected": {"stale": 1}}))
    totals.note(Status("actor", "actor-0", {"incarnation": 1, "written_off": 4, "dropped_no_credit": 2}))
    totals.note(Status("actor", "actor-0", {"incarnation": 2, "written_off": 1}))  # restarted: counts from zero
    totals.note(Status("curriculum", "curriculum", {"incarnation": 9, "dropped_inbox_full": 5,
                                                    "rejected": {"digest": 2, "bogus": -1, "odd": True}}))
    totals.note(Status("actor", "actor-1", {"incarnation": 3, "written_off": "many", "lost": 2**70}))
    expected = {"actor/written_off": 5, "actor/dropped_no_credit": 2, "curriculum/dropped_inbox_full": 5,
                "curriculum/rejected/digest": 2}
    assert totals.totals() == dict(sorted(expected.items()))

    restored = DropTotals()  # the learner restarted: the sums come back from its checkpoint
    restored.restore(totals.state())
    restored.note(Status("actor", "actor-0", {"incarnation": 2, "written_off": 6}))  # still the same process
    assert restored.totals()["actor/written_off"] == 4 + 6
    restored.restore("not a state")
    assert restored.totals()["actor/written_off"] == 10


def test_drop_totals_tell_restarts_apart_by_pid_where_no_incarnation_is_sent() -> None:
    totals = DropTotals()  # the recorder sends no incarnation; every status carries its sender's pid
    totals.note(Status("recorder", "recorder", {"pid": 100, "rejected": {"bad_shape": 2}}))
    totals.note(Status("recorder", "recorder", {"pid": 100, "rejected": {"bad_shape": 3}}))
    totals.note(Status("recorder", "recorder", {"pid": 207, "rejected": {}}))  # killed and started again
    assert totals.totals() == {"recorder/rejected/bad_shape": 3}
