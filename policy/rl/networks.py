"""The paper's networks: 400-300 LeakyReLU, tanh on the actor's output, Q(s, a) from one MLP;
and SAC's Gaussian actor, whose mean is that same actor."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional

from policy.controllers.weights import LEAKY_RELU_SLOPE
from policy.rl.exploration import LOG_STD_MAX, LOG_STD_MIN


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


class GaussianActor(Actor):
    """SAC's actor: `Actor`'s network gives the mean, a second head on its last hidden layer
    the log standard deviation; actions are tanh(mean + std N(0, 1)).

    `forward` is the deterministic tanh(mean), so what ships (`linears`, the weights file) is
    an `Actor` exactly; the log-std head (`log_std`) is training-only and is not exported.
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, int]) -> None:
        super().__init__(obs_dim, act_dim, hidden)
        self.log_std = nn.Linear(hidden[1], act_dim)

    def sample(
        self, obs: torch.Tensor, generator: torch.Generator
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised action in (-1, 1) and its log-density (batch, 1), with the tanh
        change of variables."""
        features = self.net[:4](obs)
        mean = self.net[4](features)
        log_std = squash_log_std(self.log_std(features))
        std = log_std.exp()
        noise = torch.randn(mean.shape, generator=generator)
        u = mean + std * noise
        action = torch.tanh(u)
        log_prob = -0.5 * noise**2 - log_std - 0.5 * math.log(2 * math.pi)
        # log |d tanh(u)/du| = log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), stable
        log_prob = log_prob - 2.0 * (math.log(2.0) - u - functional.softplus(-2.0 * u))
        return action, log_prob.sum(dim=1, keepdim=True)


def squash_log_std(raw: torch.Tensor) -> torch.Tensor:
    """The head's output mapped smoothly into [LOG_STD_MIN, LOG_STD_MAX] (CleanRL's SAC)."""
    return LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(raw) + 1.0)


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
