"""Which levels to train on next: level-buffer algorithms as pure functions over fixed-size arrays (domain
randomisation, PLR, robust PLR, ACCEL, SFL), used inside the fused trainer, and the curriculum service process
that scores level results from actors and serves them level batches in distributed runs."""
