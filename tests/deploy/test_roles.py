"""The roles a run's processes play come from the command table: every process command declares its role, the
router enforces them all, and `impulse router --roles` lists them for the credentials script."""

from __future__ import annotations

import subprocess
import sys

from impulse.bus.roles import FOLLOWS_WEIGHTS, LEARNER_BROADCASTS, OPERATOR_ROLE, PROTOCOL_ROLES
from impulse.deploy.commands import COMMANDS, run_roles
from tests.support.paths import REPO


def test_every_process_command_declares_its_role_and_the_run_has_each_once() -> None:
    roles = {role.name: role for role in run_roles()}
    assert len(roles) == len(run_roles())
    assert set(roles) == {"learner", "actor", "curriculum", "evaluator", "recorder", "operator"}
    assert {role.name for role in PROTOCOL_ROLES} <= set(roles)
    assert roles["operator"] == OPERATOR_ROLE
    by_command = {command.name: command.role for command in COMMANDS if command.role is not None}
    assert {name: role.name for name, role in by_command.items()} == {
        "learner": "learner", "actor": "actor", "evaluator": "evaluator", "recorder": "recorder",
        "curriculum": "curriculum"}
    # What the roles added beside the protocol may do: follow the learner; the recorder also hears the actors.
    assert roles["evaluator"].asks == FOLLOWS_WEIGHTS and roles["evaluator"].hears == LEARNER_BROADCASTS
    assert roles["recorder"].asks == ()
    assert set(roles["recorder"].hears) == {"actor/traj/*", "actor/played/*", *LEARNER_BROADCASTS}
    assert not roles["evaluator"].answers and not roles["recorder"].answers


def test_impulse_router_lists_the_roles() -> None:
    listed = subprocess.run([sys.executable, "-m", "impulse.deploy.cli", "router", "--roles"], capture_output=True,
                            text=True, cwd=REPO, timeout=120)
    assert listed.returncode == 0, listed.stderr
    assert listed.stdout.split() == [role.name for role in run_roles()]
