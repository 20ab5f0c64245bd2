"""The agent as the rest of the system sees it: a network, its action distribution and the policy function the
rollout calls. Built once from the configs; shared by the fused trainer, evaluation and (later) actors."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from impulse.engine.env.actions import action_space
from impulse.engine.env.config import EnvConfig
from impulse.engine.env.observations import observation_shape
from impulse.engine.env.spec import EnvParams, EnvSpec, env_from_config
from impulse.learner.config import NetworkConfig
from impulse.learner.distributions import Distribution, distribution_for
from impulse.learner.networks import ActorCritic, make_network

Array = jax.Array

NETWORK_OBSERVATIONS: dict[str, tuple[str, ...]] = {
    "flat": ("symbolic", "symbolic_padded", "blind"),
    "cnn": ("pixels",),
}
"""The observations each network kind takes (`env.observation`); the others take "entity"."""


@dataclass(frozen=True)
class Agent:
    """Static description of the policy (hashable, so jitted functions can take it as a static argument)."""

    network: ActorCritic
    distribution: Distribution
    spec: EnvSpec

    def apply(self, params: Any, obs: Any) -> tuple[Array, Array]:
        """(distribution parameters, value) for a batch of observations."""
        return self.network.apply(params, obs)

    def act(self, params: Any, obs: Any, key: Array) -> tuple[Array, Array, Array]:
        """Sample actions: (action, log-probability, value). The rollout's `policy`."""
        dist_params, value = self.network.apply(params, obs)
        action = self.distribution.sample(dist_params, key)
        return action, self.distribution.log_prob(dist_params, action), value

    def act_greedy(self, params: Any, obs: Any, key: Array) -> tuple[Array, Array, Array]:
        """The most likely action (for deterministic evaluation)."""
        del key
        dist_params, value = self.network.apply(params, obs)
        action = self.distribution.mode(dist_params)
        return action, self.distribution.log_prob(dist_params, action), value

    @functools.partial(jax.jit, static_argnums=0)
    def init(self, key: Array) -> Any:
        """Fresh parameters, initialised on a dummy observation of one environment. Compiled as one program, once
        per agent (the same bits as running the initialisers op by op, in about half the time, and kept in the
        compilation cache), because every process that starts a policy pays for it."""
        dummy = jax.tree.map(lambda s: jnp.zeros((1,) + s.shape, s.dtype), observation_shape(self.spec))
        return self.network.init(key, dummy)


def make_agent(network: NetworkConfig, spec: EnvSpec) -> Agent:
    takes = NETWORK_OBSERVATIONS.get(network.kind, ("entity",))
    if spec.observation not in takes:
        wanted = " or ".join(f'"{kind}"' for kind in takes)
        raise ValueError(f'network.kind "{network.kind}" needs env.observation {wanted}, got "{spec.observation}"')
    distribution = distribution_for(action_space(spec))
    shape = observation_shape(spec)
    array_dims = len(shape.shape) if isinstance(shape, jax.ShapeDtypeStruct) else 1
    return Agent(make_network(network, distribution, array_dims), distribution, spec)


class EnvAndAgent(NamedTuple):
    """A run's environment (its static spec and its parameters) and the agent that plays it."""

    spec: EnvSpec
    env_params: EnvParams
    agent: Agent


def env_and_agent(env: EnvConfig, network: NetworkConfig) -> EnvAndAgent:
    """The environment of a run's `[env]` section and the agent of its `[network]` section for it: what every
    process that plays or trains builds first (`ValueError` when the network cannot read the observations)."""
    spec, env_params = env_from_config(env)
    return EnvAndAgent(spec, env_params, make_agent(network, spec))
