"""Experiments over many episodes and arms: rollout backends, Ray campaigns, selection,
statistics."""
