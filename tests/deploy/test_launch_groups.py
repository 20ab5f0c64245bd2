"""Which of the launcher's children count as actors (the run stops once all have given up) and which are stopped
first: the recorder and the evaluator are not actors, so a run whose actors are all gone stops even while they
live."""

from pathlib import Path

from impulse.deploy.commands.launch import actor_group, followers_group, give_up_on
from impulse.deploy.runtime.supervisor import Child


def _children(tmp_path: Path) -> list[Child]:
    names = ["viewer", "learner", "curriculum", "evaluator", "recorder", "actor-0", "actor-1"]
    return [Child(name, lambda restart: ["true"], tmp_path / f"{name}.log") for name in names]


def test_actor_group_is_the_actors_alone(tmp_path):
    children = _children(tmp_path)
    assert [c.name for c in actor_group(children)] == ["actor-0", "actor-1"]
    assert [c.name for c in followers_group(children)] == ["evaluator", "actor-0", "actor-1"]


def test_the_run_stops_when_every_actor_gave_up_while_the_recorder_lives(tmp_path):
    children = _children(tmp_path)
    by_name = {c.name: c for c in children}
    actors = actor_group(children)
    by_name["actor-0"].gave_up = True
    assert give_up_on(by_name["actor-0"], actors) == []  # one actor left: the run goes on
    by_name["actor-1"].gave_up = True
    assert give_up_on(by_name["actor-1"], actors) == actors  # the recorder and the evaluator still live
    assert not by_name["recorder"].gave_up and not by_name["evaluator"].gave_up


def test_a_recorder_or_evaluator_giving_up_does_not_stop_the_run(tmp_path):
    children = _children(tmp_path)
    by_name = {c.name: c for c in children}
    for name in ("recorder", "evaluator"):
        by_name[name].gave_up = True
        assert give_up_on(by_name[name], actor_group(children)) == []
    by_name["learner"].gave_up = True
    assert give_up_on(by_name["learner"], actor_group(children)) == [by_name["learner"]]
