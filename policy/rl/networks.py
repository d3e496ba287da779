"""The paper's networks: 400-300 LeakyReLU, tanh on the actor's output, Q(s, a) from one MLP."""

from __future__ import annotations

import torch
from torch import nn

from policy.controllers.weights import LEAKY_RELU_SLOPE


class Actor(nn.Module):
    """Observation -> action in [-1, 1]^act_dim (fractions of the current limits)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, int]) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim, hidden[0]),
            nn.LeakyReLU(LEAKY_RELU_SLOPE),
            nn.Linear(hidden[0], hidden[1]),
            nn.LeakyReLU(LEAKY_RELU_SLOPE),
            nn.Linear(hidden[1], act_dim),
            nn.Tanh(),
        )

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.net(obs)
        return out

    def linears(self) -> list[nn.Linear]:
        """The dense layers in order: what the weights file stores (policy.controllers.weights)."""
        return [m for m in self.net if isinstance(m, nn.Linear)]


class Critic(nn.Module):
    """(observation, action) -> Q, the action joined to the input layer."""

    def __init__(
        self, obs_dim: int, act_dim: int, hidden: tuple[int, int], layer_norm: bool = False
    ) -> None:
        super().__init__()
        # LayerNorm after each hidden layer (`layer_norm`) keeps the features' scale fixed
        # while the values it regresses drift, a known cure for critics that stall or diverge
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, hidden[0]),
            *([nn.LayerNorm(hidden[0])] if layer_norm else []),
            nn.LeakyReLU(LEAKY_RELU_SLOPE),
            nn.Linear(hidden[0], hidden[1]),
            *([nn.LayerNorm(hidden[1])] if layer_norm else []),
            nn.LeakyReLU(LEAKY_RELU_SLOPE),
            nn.Linear(hidden[1], 1),
        )

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.net(torch.cat([obs, act], dim=1))
        return out
