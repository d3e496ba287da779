"""Exploration: Ornstein-Uhlenbeck noise, one process per env and joint (the paper's DDPG);
SAC's Gaussian samples, in numpy for the collector process.

Temporally correlated noise moves a joint for several steps in one direction, which white
noise on a current command at 20 Hz would mostly average away.
"""

from __future__ import annotations

import numpy as np

#: SAC's log standard deviation bounds, in pre-tanh action units (CleanRL's)
LOG_STD_MIN = -5.0
LOG_STD_MAX = 2.0


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


class GaussianSampler:
    """SAC's exploration outside torch: a ~ tanh(mean + std N(0, 1)) from the actor's layers.

    `arrays` is (W0, b0, W1, b1, W_mean, b_mean, W_logstd, b_logstd) in torch's layout, as
    `GaussianActor` holds them; the same computation as `GaussianActor.sample`.
    """

    def __init__(
        self, arrays: list[np.ndarray], leaky_slope: float, rng: np.random.Generator
    ) -> None:
        if len(arrays) != 8:
            raise ValueError(f"a Gaussian actor has 4 layers (8 arrays), got {len(arrays)}")
        self.w = [a.astype(np.float64).T for a in arrays[0::2]]
        self.b = [a.astype(np.float64) for a in arrays[1::2]]
        self.slope, self.rng = leaky_slope, rng

    def sample(self, obs: np.ndarray) -> np.ndarray:
        x = np.asarray(obs, dtype=np.float64)
        for i in range(2):
            x = x @ self.w[i] + self.b[i]
            x = np.maximum(x, self.slope * x)
        mean = x @ self.w[2] + self.b[2]
        raw = x @ self.w[3] + self.b[3]
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (np.tanh(raw) + 1.0)
        out: np.ndarray = np.tanh(mean + np.exp(log_std) * self.rng.standard_normal(mean.shape))
        return out
