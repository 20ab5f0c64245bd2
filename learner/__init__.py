"""Learning: the flax policy and value networks, PPO with a correction for policy lag (off-policy data from
actors), the training state, orbax checkpoints, evaluation on the hand-made levels, and the fused single-process
trainer behind `impulse train`. Its configuration lives in `learner.config`; the rest arrives with issue 5."""
