"""Replay buffer: a numpy ring that also keeps the expert's action for every state (for BC).

Each transition carries its bootstrap `discount` (policy.rl.nstep): gamma ** (rewards summed in
`rew`), 0 where the episode terminated.
"""

from __future__ import annotations

import numpy as np


class ReplayBuffer:
    """Fixed-capacity ring of transitions; numpy rather than torch: sampling is cheaper."""

    FIELDS = ("obs", "act", "rew", "next_obs", "discount", "expert")

    def __init__(self, capacity: int, obs_dim: int, act_dim: int) -> None:
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.act = np.zeros((capacity, act_dim), np.float32)
        self.rew = np.zeros((capacity, 1), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.discount = np.zeros((capacity, 1), np.float32)
        self.expert = np.zeros((capacity, act_dim), np.float32)
        self.pos = 0
        self.full = False

    def __len__(self) -> int:
        return self.capacity if self.full else self.pos

    def add(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        next_obs: np.ndarray,
        discount: np.ndarray,
        expert: np.ndarray,
    ) -> None:
        """Add a batch of transitions (first axis = env)."""
        n = len(obs)
        idx = (self.pos + np.arange(n)) % self.capacity
        self.obs[idx] = obs
        self.act[idx] = act
        self.rew[idx, 0] = rew
        self.next_obs[idx] = next_obs
        self.discount[idx, 0] = discount
        self.expert[idx] = expert
        self.full = self.full or self.pos + n >= self.capacity
        self.pos = int((self.pos + n) % self.capacity)

    def sample(self, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        idx = rng.integers(0, len(self), size=n)
        return {name: getattr(self, name)[idx] for name in self.FIELDS}

    def state(self) -> dict[str, np.ndarray]:
        """The filled part and the ring position, for a checkpoint."""
        size = len(self)
        data = {name: getattr(self, name)[:size] for name in self.FIELDS}
        data["meta"] = np.array([self.pos, int(self.full), self.capacity])
        return data

    def load(self, data: dict[str, np.ndarray], gamma: float) -> None:
        """`state()`'s arrays; a buffer saved before discounts were stored holds `term`
        instead, read as one-step transitions with `gamma`."""
        if "discount" not in data and "term" in data:
            data = {**data, "discount": gamma * (1.0 - data["term"])}
        pos, full, capacity = (int(x) for x in data["meta"])
        if capacity != self.capacity:
            raise ValueError(f"buffer capacity {capacity} in checkpoint, {self.capacity} now")
        size = len(data["obs"])
        for name in self.FIELDS:
            getattr(self, name)[:size] = data[name]
        self.pos, self.full = pos, bool(full)
