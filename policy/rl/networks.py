"""The paper's networks: 400-300 LeakyReLU, tanh on the actor's output, Q(s, a) from one MLP;
SAC's Gaussian actor, whose mean is that same actor; and CrossQ's critic, the same MLP with
batch renormalisation (`BatchRenorm`) before each layer."""

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


class BatchRenorm(nn.Module):
    """Batch renormalisation (Ioffe 2017), as CrossQ's critic uses it.

    In training a batch is normalised by its own mean and spread, corrected towards the
    running ones by r (spread ratio) and d (mean offset), both clipped and carrying no
    gradient; the clips open from r = 1, d = 0 (plain batch normalisation) to [1/3, 3] and
    [-5, 5] over `warmup` training batches. In eval mode the running statistics alone
    normalise, so one state's value does not depend on the rest of its batch."""

    def __init__(
        self, features: int, warmup: int, momentum: float = 0.01, eps: float = 1e-3
    ) -> None:
        super().__init__()
        self.warmup, self.momentum, self.eps = warmup, momentum, eps
        self.weight = nn.Parameter(torch.ones(features))
        self.bias = nn.Parameter(torch.zeros(features))
        self.running_mean: torch.Tensor
        self.running_var: torch.Tensor
        self.batches: torch.Tensor
        self.register_buffer("running_mean", torch.zeros(features))
        self.register_buffer("running_var", torch.ones(features))
        self.register_buffer("batches", torch.zeros((), dtype=torch.long))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        running_std = (self.running_var + self.eps).sqrt()
        if not self.training:
            return self.weight * (x - self.running_mean) / running_std + self.bias
        mean = x.mean(dim=0)
        var = x.var(dim=0, unbiased=False)
        std = (var + self.eps).sqrt()
        opened = min(1.0, float(self.batches) / self.warmup) if self.warmup > 0 else 1.0
        r_max, d_max = 1.0 + 2.0 * opened, 5.0 * opened
        r = (std / running_std).detach().clamp(1.0 / r_max, r_max)
        d = ((mean - self.running_mean) / running_std).detach().clamp(-d_max, d_max)
        out = self.weight * ((x - mean) / std * r + d) + self.bias
        with torch.no_grad():
            self.running_mean.lerp_(mean.detach(), self.momentum)
            self.running_var.lerp_(x.detach().var(dim=0, unbiased=True), self.momentum)
            self.batches += 1
        return out


class Critic(nn.Module):
    """(observation, action) -> Q, the action joined to the input layer."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: tuple[int, int],
        layer_norm: bool = False,
        renorm_warmup: int | None = None,
    ) -> None:
        super().__init__()
        # LayerNorm after each hidden layer (`layer_norm`) keeps the features' scale fixed
        # while the values it regresses drift, a known cure for critics that stall or diverge;
        # CrossQ's batch renormalisation (`renorm_warmup` not None) goes before every layer
        renorm = renorm_warmup is not None

        def norm(features: int) -> list[nn.Module]:
            if renorm:
                assert renorm_warmup is not None
                return [BatchRenorm(features, renorm_warmup)]
            return []

        self.net = nn.Sequential(
            *norm(obs_dim + act_dim),
            nn.Linear(obs_dim + act_dim, hidden[0]),
            *([nn.LayerNorm(hidden[0])] if layer_norm else []),
            nn.LeakyReLU(LEAKY_RELU_SLOPE),
            *norm(hidden[0]),
            nn.Linear(hidden[0], hidden[1]),
            *([nn.LayerNorm(hidden[1])] if layer_norm else []),
            nn.LeakyReLU(LEAKY_RELU_SLOPE),
            *norm(hidden[1]),
            nn.Linear(hidden[1], 1),
        )

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.net(torch.cat([obs, act], dim=1))
        return out
