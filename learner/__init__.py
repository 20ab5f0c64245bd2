"""Learning: the flax policy and value networks, PPO with a correction for policy lag (off-policy data from
actors), the training state, orbax checkpoints, evaluation on the hand-made levels, the fused single-process
trainer behind `impulse train`, and the learner service of distributed runs. Its configuration lives in
`learner.config`."""
