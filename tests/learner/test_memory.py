"""A program that does not fit is refused after compiling, before it runs (engine/memory.py): XLA's own account of
the compiled program against the memory free, with the overrides that would fit; the training step of `impulse
train`, and the learner service's update and an actor's rollout in `impulse launch`."""

from __future__ import annotations

import re
from functools import partial

import jax
import jax.numpy as jnp
import pytest

from impulse.actors.levels import LocalLevels
from impulse.actors.process import Actor, actor_name
from impulse.bus.roles import ACTOR_ROLE
from impulse.bus.session import Bus
from impulse.deploy.cli import main
from impulse.deploy.config import resolve_config
from impulse.deploy.run_config import RunConfig
from impulse.deploy.runtime.exit_codes import EXIT_CANNOT_RUN
from impulse.engine import memory
from impulse.engine.env.spec import env_from_config
from impulse.engine.memory import DoesNotFit, check_fits, free_bytes, program_bytes
from impulse.learner.agent import make_agent
from impulse.learner.curriculum_inputs import batch_level_results
from tests.support.launch_procs import QUICK_LAUNCH, free_port

SMALL = ("ppo.num_envs=8", "ppo.num_steps=8", "ppo.num_minibatches=1", "env.observation=symbolic", "network.kind=flat",
         "network.width=16", "network.depth=1")
"""Quick-launch at a size whose programs compile fastest: a small flat network on the symbolic observation (the
refusals do not depend on the network)."""


@pytest.fixture(scope="module")
def compiled():
    def rollout(x):  # a scan whose stacked outputs are the "rollout buffer": 64 x 256 x 256 float32 = 16 MiB
        return jax.lax.scan(lambda c, _: (jnp.tanh(c), jnp.tanh(c)), x, None, length=64)

    return jax.jit(rollout).lower(jnp.ones((256, 256))).compile()


def test_the_compiled_programs_size_is_read_from_xla(compiled) -> None:
    need = program_bytes(compiled)
    assert need is not None and 16 * 2**20 <= need < 64 * 2**20, need
    assert free_bytes() > 2**20  # this machine has more than a megabyte free


def test_a_step_that_does_not_fit_is_refused_with_sizes_and_an_override(compiled) -> None:
    with pytest.raises(DoesNotFit, match=r"the training step needs about 0\.0 GiB \(2,048 envs x 256 steps per "
                                         r"update\).*use fewer, for example ppo.num_envs=\d+"):
        check_fits(compiled, "the training step", 2048, 256, free=4 * 2**20)
    check_fits(compiled, "the training step", 2048, 256, free=2**30)  # fits: no complaint


def test_processes_of_a_launch_plan_for_their_share_of_a_cpu_host(compiled, monkeypatch) -> None:
    """`impulse launch` tells its children how many of them share the host (IMPULSE_HOST_PROCESSES): on a CPU each
    checks against its share of the free memory, so that together they cannot plan for more than there is."""
    check_fits(compiled, "the rollout", 256, 64, free=2**30)  # alone: 16 to 64 MiB of 1 GiB
    monkeypatch.setenv(memory.HOST_PROCESSES_ENV, "64")
    assert memory.host_share() == 64
    with pytest.raises(DoesNotFit, match=r"of the 0\.0 GiB free on cpu \(its 1/64 share: 64 processes of this run"):
        check_fits(compiled, "the rollout", 256, 64, free=2**30)  # 16 MiB each


def test_the_learner_refuses_an_update_that_does_not_fit_and_takes_back_its_new_run(tmp_path, monkeypatch,
                                                                                       capsys) -> None:
    """`impulse learner` compiles its update when it starts and checks it the same way (here against 4 KiB free),
    so an `impulse launch` at GPU sizes on a CPU stops with the sizes instead of being killed later (exit status
    78: the launcher gives up at once). The run directory it made for this new run goes again: nothing trained."""
    run_dir = tmp_path / "new-run"
    monkeypatch.setattr(memory, "free_bytes", lambda device=None: 2**12)
    code = main(["learner", "--hub", "--config", str(QUICK_LAUNCH), f"run_dir={run_dir}",
                 f"bus.hub=tcp/127.0.0.1:{free_port()}", *SMALL])
    err = capsys.readouterr().err
    assert code == EXIT_CANNOT_RUN, err
    assert re.search(r"impulse learner: the learner's update needs about .* \(8 envs x 8 steps per update", err), err
    assert f"removed {run_dir}, created for this run: nothing was trained" in err and not run_dir.exists()


class CompileCounter:
    """How often JAX lowered a function of a given name for compiling (each new program is lowered once, whether
    XLA then compiles it or finds it in the persistent cache)."""

    def __init__(self, name: str):
        self.fun_name, self.count = f"jit({name})", 0

    def __call__(self, event: str, duration: float, **kwargs) -> None:
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration" and kwargs.get("fun_name") == self.fun_name:
            self.count += 1


def test_an_actor_refuses_a_rollout_that_does_not_fit_and_compiles_it_only_once(monkeypatch) -> None:
    """An actor compiles its rollout when it starts and checks it the same way (here against 4 KiB free), so
    `impulse launch` at GPU sizes on a CPU stops its actors with the sizes (and gives up on them at once: exit
    status 78). With room, the first rollout runs the program `start` compiled: no second compile."""
    config = resolve_config(RunConfig, QUICK_LAUNCH, [f"bus.hub=tcp/127.0.0.1:{free_port()}", *SMALL])
    spec, env_params = env_from_config(config.env)
    agent = make_agent(config.network, spec)
    counter = CompileCounter("actor_rollout")
    jax.monitoring.register_event_duration_secs_listener(counter)
    try:
        with Bus(config.bus, "memory-test", ACTOR_ROLE.name, actor_name(0), listen=True) as bus:

            def new_actor() -> Actor:
                return Actor(config.actors, num_envs=8, num_steps=8, seed=0, index=0, bus=bus, agent=agent,
                             env_params=env_params, levels=LocalLevels(config.env, spec.sizes),
                             level_results=partial(batch_level_results, agent, config.ppo))

            with monkeypatch.context() as patched:
                patched.setattr(memory, "free_bytes", lambda device=None: 2**12)
                with pytest.raises(DoesNotFit, match=r"actor-0's rollout needs about .* \(8 envs x 8 steps per "
                                                     r"update\), more than 80% of the 0\.0 GiB free.*ppo\.num_envs="):
                    new_actor().start()
            assert counter.count == 1

            actor = new_actor()  # the same sizes, with room: the first rollout runs the program `start` compiled
            actor.start()
            assert counter.count == 2
            actor.follow.params = agent.init(jax.random.PRNGKey(1))  # as if the learner's first weights had come
            report = actor.cycle()
            assert report is not None and report.env_steps == 64
            assert counter.count == 2, "the first rollout compiled its program again"
    finally:
        jax.monitoring.unregister_event_duration_listener(counter)
