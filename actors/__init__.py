"""Experience collection: the rollout function (policy and environment stepped together in one `lax.scan`,
written once and shared by the fused trainer and the distributed actors) and the actor process loop that adopts
new weights, runs rollouts, and publishes trajectories to the learner and level results to the curriculum."""
