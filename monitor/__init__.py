"""Watching a run in Rerun: drawing scenes from engine geometry, streaming rollouts and metrics, the default
viewer blueprint, and the `impulse view` command's viewer side."""
