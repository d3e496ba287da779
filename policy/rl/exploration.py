"""Exploration noise: Ornstein-Uhlenbeck, one process per env and joint (the paper's DDPG).

Temporally correlated noise moves a joint for several steps in one direction, which white
noise on a current command at 20 Hz would mostly average away.
"""

from __future__ import annotations

import numpy as np


class OUNoise:
    """x <- x - theta x + sigma N(0, 1), per element of `shape` (envs x joints)."""

    def __init__(
        self, shape: tuple[int, ...], theta: float, sigma: float, rng: np.random.Generator
    ) -> None:
        self.theta, self.sigma, self.rng = theta, sigma, rng
        self.state = np.zeros(shape)

    def reset(self, index: int | None = None) -> None:
        """Zero every process, or only env `index`'s (its episode restarted)."""
        if index is None:
            self.state[:] = 0.0
        else:
            self.state[index] = 0.0

    def sample(self) -> np.ndarray:
        self.state += -self.theta * self.state + self.sigma * self.rng.standard_normal(
            self.state.shape
        )
        return self.state.copy()
