"""The Kinetix-compatible task layer over the physics engine: which level is played, what the agent observes, how
its actions drive motors and thrusters, the reward, and auto-reset at episode end.

Pure functions, jitted with the static `EnvSpec` and vmappable over environments (`engine.env.env` documents the
order of one step and the auto-reset rule):

    from impulse.engine.env.env import reset_batch, step
    from impulse.engine.env.spec import env_from_config

    spec, params = env_from_config(config)                              # config: EnvConfig
    obs, state = reset_batch(spec, params, levels, num_envs)            # levels: a Level batch [K]
    obs, state, reward, done, info = jax.vmap(step, in_axes=(None, None, 0, 0, None))(
        spec, params, state, actions, levels)

Modules: `config` (EnvConfig, plain settings), `spec` (EnvSpec, EnvParams, env_from_config), `state` (EnvState),
`actions` (action types, action spaces, bindings), `observations` (entity, flat symbolic and pixel observations),
`pixels` (drawing the scene as Kinetix's pixel observation), `observation_types` (the observation layouts),
`reward` (sparse outcome and dense shaping), `env` (reset, step), `api` (`make_env`: the public, gymnax-style face
over reset and step),
`episodes` (the one episode loop: E environments stepped for T steps with caller-chosen actions, and the outcome of
each one's first episode), `scripted` (playing the hand-made levels' scripted controllers).
This package file imports nothing, so reading the configuration does not load JAX.
"""
