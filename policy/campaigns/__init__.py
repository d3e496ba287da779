"""Experiments over many episodes and arms: rollout backends, Ray campaigns, selection,
statistics, and the identification of an arm through the driver (`identification`, and
`identify`: many hidden arms identified on Ray)."""
