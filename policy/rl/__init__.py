"""Reinforcement learning: the environment, networks, agent, replay, trainer and its config."""
