"""The Kinetix-compatible task layer over the physics engine: which levels are played, what the agent observes,
how its actions drive motors and thrusters, the reward, and auto-reset at episode end. For now it holds only
its configuration (`engine.env.config`); the environment itself arrives with issue 4."""
