"""The simulation room: the physics engine (`engine.physics`), the Kinetix-compatible task layer (`engine.env`:
levels, observations, actions, reward, auto-reset), level generation, mutation and level files
(`engine.levels`), our hand-made levels and the scene geometry used for drawing. It imports nothing else of
ours, only jax and numpy, so every other room can build on it and it can be tested and benchmarked alone."""
