"""The launcher's children, their groups, their stop order and the rule of giving up all come from the process
role registry (`deploy.runtime.process_roles`): the recorder and the evaluator are not actors, so a run whose actors
are all gone stops even while they live, and a role added to the registry alone is started, stopped in its stage
and given up on by its kind, with no other edit."""

from dataclasses import replace
from pathlib import Path

from impulse.deploy.commands.launch import give_up_on
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.process_roles import (
    PROCESS_ROLES,
    RECORDER_ROLE,
    Kind,
    LaunchPlan,
    credential_roles,
    group,
    jax_processes,
    launch_children,
    launch_summary,
    parts_by_child,
    stop_stages,
)


def _plan(tmp_path: Path, *overrides: str, record: bool = True) -> LaunchPlan:
    config = resolve_config(RunConfig, None, ["env.levels=random", "curriculum.method=sfl", "actors.num_actors=2",
                                        "evaluator.levels=handmade:s", f"recorder.path={tmp_path / 'data'}",
                                        *overrides])
    return LaunchPlan(config, tmp_path / "run", resume=False, record=tmp_path / "run.rrd" if record else None)


def test_the_children_and_their_command_lines_come_from_the_registry(tmp_path):
    plan = _plan(tmp_path)
    children = launch_children(plan)
    assert [c.name for c in children] == ["viewer", "learner", "curriculum", "evaluator", "recorder", "actor-0",
                                          "actor-1"]
    by_name = {c.name: c for c in children}
    assert by_name["learner"].argv(False)[-2:] == ["--run", str(plan.run_dir)]
    assert by_name["learner"].argv(True)[-1] == "--resume"  # a restarted learner resumes
    assert by_name["actor-1"].argv(False)[-2:] == ["--index", "1"]
    assert by_name["viewer"].argv(False)[-1] == "--headless"  # --record without --view
    assert by_name["curriculum"].log_path == plan.run_dir / "logs" / "curriculum.log"
    assert launch_summary(plan) == ["learner", "curriculum (sfl)", "evaluator (handmade:s)",
                                    f"recorder ({tmp_path / 'data'})", "2 actors"]
    assert credential_roles(plan) == ["learner", "curriculum", "evaluator", "recorder", "actor"]
    assert jax_processes(children) == 5  # neither the viewer nor the recorder runs batch-sized programs
    assert parts_by_child(children)["viewer"] is None  # it publishes no status
    # A run without a curriculum service, evaluator, recorder or stream starts the learner and its actors only.
    plain = launch_children(_plan(tmp_path, "env.levels=handmade:s", "curriculum.method=dr", "evaluator.levels=",
                                  "recorder.path=", record=False))
    assert [c.name for c in plain] == ["learner", "actor-0", "actor-1"]


def test_stop_order_and_groups(tmp_path):
    children = launch_children(_plan(tmp_path))
    assert [c.name for c in group(children, Kind.FOLLOWER)] == ["actor-0", "actor-1"]
    stages = [[c.name for c in members] for _, members in stop_stages(children)]
    assert stages == [["evaluator", "actor-0", "actor-1"], ["recorder"], ["curriculum"], ["learner"], ["viewer"]]
    [(lead, _)] = [stage for stage in stop_stages(children) if stage[1][0].name == "learner"]
    assert lead.stop_timeout_s == 180.0 and lead.stop_note  # the learner gets time for its final checkpoint


def test_the_run_stops_when_every_actor_gave_up_while_the_recorder_lives(tmp_path):
    children = launch_children(_plan(tmp_path))
    by_name = {c.name: c for c in children}
    by_name["actor-0"].gave_up = True
    assert give_up_on(by_name["actor-0"], children) == []  # one actor left: the run goes on
    by_name["actor-1"].gave_up = True
    assert give_up_on(by_name["actor-1"], children) == [by_name["actor-0"], by_name["actor-1"]]
    assert not by_name["recorder"].gave_up and not by_name["evaluator"].gave_up


def test_a_recorder_or_evaluator_giving_up_does_not_stop_the_run(tmp_path):
    children = launch_children(_plan(tmp_path))
    by_name = {c.name: c for c in children}
    for name in ("recorder", "evaluator", "viewer"):
        by_name[name].gave_up = True
        assert give_up_on(by_name[name], children) == []
    for name in ("learner", "curriculum"):
        by_name[name].gave_up = True
        assert give_up_on(by_name[name], children) == [by_name[name]]


def test_a_role_added_to_the_registry_alone_is_started_stopped_and_given_up_on_by_its_entry(tmp_path):
    """A toy role: a second recorder-like sidecar of two processes, stopped between the curriculum and the
    learner; then the same role made critical."""
    toy = replace(RECORDER_ROLE, name="toy", several=True, count=lambda plan: 2, stop_stage=2.5,
                  describe=lambda config: "2 toys")
    roles = (*PROCESS_ROLES, toy)
    plan = _plan(tmp_path, record=False)
    children = launch_children(plan, roles)
    assert [c.name for c in children][-2:] == ["toy-0", "toy-1"]
    stages = [[c.name for c in members] for _, members in stop_stages(children, roles)]
    assert stages.index(["toy-0", "toy-1"]) == stages.index(["curriculum"]) + 1
    assert stages.index(["learner"]) == stages.index(["toy-0", "toy-1"]) + 1
    by_name = {c.name: c for c in children}
    by_name["toy-0"].gave_up = True
    assert give_up_on(by_name["toy-0"], children, roles) == []  # a sidecar: the run goes on
    critical = (*PROCESS_ROLES, replace(toy, kind=Kind.CRITICAL))
    assert give_up_on(by_name["toy-0"], children, critical) == [by_name["toy-0"]]
    assert launch_summary(plan, roles)[-2:] == ["2 actors", "2 toys"]
