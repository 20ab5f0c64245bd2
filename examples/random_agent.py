"""A random agent on Impulse's hand-made S levels, through the environment API (`impulse.make_env`): 64
environments stepped side by side for one 64-step episode's worth of steps, jitted and vmapped as any gymnax
environment.

    python examples/random_agent.py
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

import impulse

NUM_ENVS = 64


def main() -> None:
    env = impulse.make_env(levels="handmade", size="s", max_timesteps=64)  # short episodes for a quick look
    print(f"{env.num_levels} levels, actions {env.action_space.kind} {env.action_space.shape}")
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.jit(jax.vmap(env.step))
    sample = jax.vmap(env.sample_action)

    key = jax.random.PRNGKey(0)
    key, reset_key = jax.random.split(key)
    obs, state = reset(jax.random.split(reset_key, NUM_ENVS))
    episodes = solved = 0
    for _ in range(env.spec.max_timesteps):
        key, action_key, step_key = jax.random.split(key, 3)
        actions = sample(jax.random.split(action_key, NUM_ENVS))
        obs, state, reward, done, info = step(jax.random.split(step_key, NUM_ENVS), state, actions)
        episodes += int(done.sum())
        solved += int(jnp.sum(info["solved"]))
    print(f"{episodes} episodes finished, {solved} solved ({solved / max(episodes, 1):.0%}) by the random agent")


if __name__ == "__main__":
    main()
