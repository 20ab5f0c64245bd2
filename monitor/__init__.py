"""Watching a run in Rerun: drawing scenes from engine geometry, streaming rollouts and metrics, the default
viewer blueprint, and the `impulse view` command's viewer side; and each run's metrics as TensorBoard scalars
and W&B history (`monitor.scalars`)."""
