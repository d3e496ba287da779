"""The DDPG agent: networks, target networks, optimisers and one gradient update.

`Agent.update` reads top to bottom like CleanRL's `ddpg_continuous_action.py`: the critic
loss against the target networks' bootstrap, then (every `policy_delay` updates) the actor
loss and the soft update of the targets. The TD3 and TD3+BC options (docs/training.md,
docs/distilled.md) are branches inside those steps, each off in `DDPGConfig.paper()`.
`Agent.update_sac` is SAC's update (`Algorithm.SAC`), read the same way as CleanRL's
`sac_continuous_action.py`: a soft TD target, the actor's entropy-regularised loss and the
temperature's. With `crossq_critic` the DDPG update takes CrossQ's critic (Bhatt et al. 2024):
batch-renormalised, no target networks, the TD target from the online critic's value of
(s', pi(s')) computed in the same batch as Q(s, a).

Speed (tools/bench_train.py): fused Adam, gradients of the actor loss for the actor only, and a
foreach lerp for the target networks.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from policy.rl.checkpoint import load_actor_npz
from policy.rl.config import Algorithm, DDPGConfig
from policy.rl.networks import Actor, Critic, GaussianActor
from policy.rl.smoothness import input_noise_std, spatial_loss, temporal_loss
from protocol.alpha5 import N_JOINTS


def _adam(params: Any, lr: float, beta1: float = 0.9) -> torch.optim.Adam:
    betas = (beta1, 0.999)
    try:
        return torch.optim.Adam(params, lr=lr, betas=betas, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr, betas=betas)


class Agent:
    def __init__(self, config: DDPGConfig, obs_dim: int, act_dim: int = N_JOINTS) -> None:
        self.config = config
        torch.manual_seed(config.seed)
        sac = config.algorithm is Algorithm.SAC
        self.actor = (GaussianActor if sac else Actor)(obs_dim, act_dim, config.hidden)
        n_critics = 2 if config.twin_critics else 1
        renorm = config.crossq_warmup_updates if config.crossq_critic else None
        self.critics = nn.ModuleList(
            Critic(obs_dim, act_dim, config.hidden, config.critic_layer_norm, renorm)
            for _ in range(n_critics)
        )
        self.actor_target = copy.deepcopy(self.actor)
        self.critics_target = copy.deepcopy(self.critics)
        for p in [*self.actor_target.parameters(), *self.critics_target.parameters()]:
            p.requires_grad_(False)
        #: the Polyak-averaged actor (`actor_average_tau`): smooths the update-to-update
        #: wander of the online actor's weights, which is what checkpoints then score
        self.actor_average: Actor | None = None
        if config.actor_average_tau > 0:
            self.actor_average = copy.deepcopy(self.actor)
            for p in self.actor_average.parameters():
                p.requires_grad_(False)
        self.actor_opt = _adam(self.actor.parameters(), config.actor_lr, config.adam_beta1)
        self.critic_opt = _adam(self.critics.parameters(), config.critic_lr, config.adam_beta1)
        #: SAC's entropy temperature, learned as log alpha (unused by DDPG)
        self.log_alpha = torch.tensor(float(np.log(config.sac_alpha)), requires_grad=True)
        self.alpha_opt = _adam([self.log_alpha], config.sac_alpha_lr)
        self.target_entropy = (
            -float(act_dim) if config.sac_target_entropy is None else config.sac_target_entropy
        )
        self.updates = 0
        #: the target policy noise's (SAC: the actor's samples') own generator: it does not
        #: shift torch's global stream
        self.gen = torch.Generator().manual_seed(config.seed + 1)
        #: per input, the sensor noise's spread (the spatial smoothness term's perturbation)
        self.input_noise: torch.Tensor | None = None
        if config.smooth_spatial_weight > 0:
            self.input_noise = torch.from_numpy(input_noise_std(config.env))
            if self.input_noise.shape != (obs_dim,):
                raise ValueError(
                    f"the env's observation has {self.input_noise.shape[0]} inputs, the actor "
                    f"{obs_dim}"
                )

    def load_actor_npz(self, path: str | Path) -> None:
        """Actor, target and averaged actor from shipped-format weights."""
        load_actor_npz(self.actor, path)
        self.actor_target.load_state_dict(self.actor.state_dict())
        if self.actor_average is not None:
            self.actor_average.load_state_dict(self.actor.state_dict())

    def set_learning_rates(self, env_steps: int) -> None:
        decay = self.config.lr_decay ** (env_steps // self.config.lr_decay_every)
        for group in self.actor_opt.param_groups:
            group["lr"] = self.config.actor_lr * decay
        for group in self.critic_opt.param_groups:
            group["lr"] = self.config.critic_lr * decay
        for group in self.alpha_opt.param_groups:
            group["lr"] = self.config.sac_alpha_lr

    def gaussian_actor(self) -> GaussianActor:
        """The actor as SAC's (`Algorithm.SAC`); an error for a DDPG agent."""
        if not isinstance(self.actor, GaussianActor):
            raise ValueError("a DDPG agent has no Gaussian actor")
        return self.actor

    @torch.no_grad()
    def explore(self, obs: np.ndarray) -> np.ndarray:
        """SAC's exploration: an action sampled from the Gaussian actor."""
        action, _ = self.gaussian_actor().sample(torch.from_numpy(obs), self.gen)
        out: np.ndarray = action.numpy()
        return out

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> np.ndarray:
        out: np.ndarray = self.actor(torch.from_numpy(obs)).numpy()
        return out

    @torch.no_grad()
    def act_average(self, obs: np.ndarray) -> np.ndarray:
        """The Polyak-averaged actor's action (`actor_average_tau` > 0)."""
        if self.actor_average is None:
            raise ValueError("actor_average_tau is 0: there is no averaged actor")
        out: np.ndarray = self.actor_average(torch.from_numpy(obs)).numpy()
        return out

    def update(self, batch: dict[str, np.ndarray], bc_weight: float) -> dict[str, float]:
        """One gradient update from `batch` (policy.rl.replay fields); returns the losses."""
        cfg = self.config
        if cfg.algorithm is Algorithm.SAC:
            return self.update_sac(batch)
        obs, act, rew, next_obs, discount = (
            torch.from_numpy(batch[k]) for k in ("obs", "act", "rew", "next_obs", "discount")
        )

        # 1. the TD target: r + gamma Q'(s', pi'(s')), cut only where the episode terminated;
        #    `discount` is gamma (0 if terminated), or gamma^n with n-step returns in r.
        #    CrossQ: the online actor and critic in place of the targets
        crossq = cfg.crossq_critic
        with torch.no_grad():
            next_act = (self.actor if crossq else self.actor_target)(next_obs)
            if cfg.target_noise > 0:  # TD3 target policy smoothing
                noise = torch.randn(next_act.shape, generator=self.gen) * cfg.target_noise
                noise = noise.clamp(-cfg.target_noise_clip, cfg.target_noise_clip)
                next_act = (next_act + noise).clamp(-1.0, 1.0)

        # 2. the critic loss: mean squared TD error, summed over the critics
        if crossq:
            info = self._crossq_critic_step(obs, act, rew, discount, next_obs, next_act)
        else:
            with torch.no_grad():
                # one critic: itself; TD3's twin critics: the smaller
                target = rew + discount * self._target_q(next_obs, next_act)
            info = self._critic_step(obs, act, target)
        if self.updates % cfg.policy_delay != 0:  # TD3: the actor and targets wait
            return info

        # 3. the actor loss: -Q(s, pi(s)), plus TD3+BC's pull towards the expert's action and
        #    CAPS's smoothness terms, where configured. CrossQ's critic values the actor's
        #    actions by its running statistics (eval mode), not by this batch's
        pi = self.actor(obs)
        if crossq:
            self.critics.eval()
        q_pi = self.critics[0](obs, pi)
        self.critics.train()
        if bc_weight > 0:
            # the Q term is made scale-free so bc_weight means the same all run
            lam = cfg.q_weight / q_pi.abs().mean().detach().clamp(min=1e-6)
            expert = torch.from_numpy(batch["expert"])
            # rows without a label (NaN: the demonstrator is no teacher there) add no BC
            labelled = ~torch.isnan(expert).any(dim=1, keepdim=True)
            expert = torch.nan_to_num(expert)
            diff = pi - expert
            if cfg.bc_relative > 0:
                diff = diff / (expert.abs() + cfg.bc_relative)
            diff = diff * labelled
            bc = (diff**2).sum() / (labelled.sum().clamp(min=1) * diff.shape[1])
            actor_loss = -lam * q_pi.mean() + bc_weight * bc
            info["bc_loss"] = float(bc.detach())
        else:
            actor_loss = -q_pi.mean()
        # CAPS: answer sensor noise and consecutive states alike (policy/rl/smoothness.py)
        if self.input_noise is not None:
            spatial = spatial_loss(self.actor, obs, pi, self.input_noise, self.gen)
            actor_loss = actor_loss + cfg.smooth_spatial_weight * spatial
            info["spatial_loss"] = float(spatial.detach())
        if cfg.smooth_temporal_weight > 0:
            temporal = temporal_loss(self.actor, pi, next_obs)
            actor_loss = actor_loss + cfg.smooth_temporal_weight * temporal
            info["temporal_loss"] = float(temporal.detach())
        self.actor_opt.zero_grad(set_to_none=True)
        # gradients for the actor only: the critic weights need none here (saves ~1/3 of the
        # critic backward pass)
        actor_loss.backward(inputs=list(self.actor.parameters()))
        self.actor_opt.step()
        info["actor_loss"] = float(actor_loss.detach())

        # 4. soft update of the targets: theta' <- theta' + tau (theta - theta'); CrossQ has none
        if not crossq:
            with torch.no_grad():
                for net, target_net in (
                    (self.actor, self.actor_target),
                    (self.critics, self.critics_target),
                ):
                    torch._foreach_lerp_(
                        list(target_net.parameters()), list(net.parameters()), cfg.tau
                    )
        self._follow_average()
        return info

    def update_sac(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        """One SAC update (Haarnoja et al. 2018, with a learned temperature)."""
        cfg = self.config
        actor = self.gaussian_actor()
        obs, act, rew, next_obs, discount = (
            torch.from_numpy(batch[k]) for k in ("obs", "act", "rew", "next_obs", "discount")
        )
        alpha = self.log_alpha.detach().exp()

        # 1. the soft TD target: r + gamma (min_i Q'_i(s', a') - alpha log pi(a'|s')),
        #    a' sampled from the current actor (SAC has no target actor)
        with torch.no_grad():
            next_act, next_log_prob = actor.sample(next_obs, self.gen)
            q_next = self._target_q(next_obs, next_act)
            target = rew + discount * (q_next - alpha * next_log_prob)

        # 2. the critic loss: mean squared TD error, summed over the critics
        info = {**self._critic_step(obs, act, target), "alpha": float(alpha)}
        if self.updates % cfg.policy_delay != 0:
            return info

        # 3. the actor loss: alpha log pi(a|s) - min_i Q_i(s, a), a reparameterised sample
        pi, log_prob = actor.sample(obs, self.gen)
        q_pi = torch.min(torch.stack([c(obs, pi) for c in self.critics]), dim=0).values
        actor_loss = (alpha * log_prob - q_pi).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward(inputs=list(actor.parameters()))
        self.actor_opt.step()
        info["actor_loss"] = float(actor_loss.detach())
        info["entropy"] = float(-log_prob.detach().mean())

        # 4. the temperature: raised while the policy's entropy is below the target, lowered
        #    while above it
        alpha_loss = -(self.log_alpha.exp() * (log_prob.detach() + self.target_entropy)).mean()
        self.alpha_opt.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_opt.step()

        # 5. soft update of the critics' targets (and the averaged actor, if kept)
        with torch.no_grad():
            torch._foreach_lerp_(
                list(self.critics_target.parameters()), list(self.critics.parameters()), cfg.tau
            )
        self._follow_average()
        return info

    def _target_q(self, next_obs: torch.Tensor, next_act: torch.Tensor) -> torch.Tensor:
        """The target critics' value of (s', a'): the smaller of two (twin critics)."""
        qs = torch.stack([c(next_obs, next_act) for c in self.critics_target])
        return torch.min(qs, dim=0).values

    def _critic_step(
        self, obs: torch.Tensor, act: torch.Tensor, target: torch.Tensor
    ) -> dict[str, float]:
        """One step of the critics towards `target`: the mean squared TD error, summed."""
        return self._fit_critics([c(obs, act) for c in self.critics], target)

    def _fit_critics(self, qs: list[torch.Tensor], target: torch.Tensor) -> dict[str, float]:
        """One optimiser step on the critics' summed mean squared TD error."""
        critic_loss = sum(((q - target) ** 2).mean() for q in qs)
        assert isinstance(critic_loss, torch.Tensor)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        return {"critic_loss": float(critic_loss.detach()), "q": float(qs[0].detach().mean())}

    def _crossq_critic_step(
        self,
        obs: torch.Tensor,
        act: torch.Tensor,
        rew: torch.Tensor,
        discount: torch.Tensor,
        next_obs: torch.Tensor,
        next_act: torch.Tensor,
    ) -> dict[str, float]:
        """CrossQ's critic step: (s, a) and (s', a') through each critic as one batch, so its
        batch renormalisation sees both; the TD target is r + gamma times the (smaller, with
        twin critics) value of the second half, without gradient."""
        n = obs.shape[0]
        both_obs, both_act = torch.cat([obs, next_obs]), torch.cat([act, next_act])
        outs = [c(both_obs, both_act) for c in self.critics]
        with torch.no_grad():
            q_next = torch.min(torch.stack([out[n:] for out in outs]), dim=0).values
            target = rew + discount * q_next
        qs = [out[:n] for out in outs]
        return self._fit_critics(qs, target)

    @torch.no_grad()
    def _follow_average(self) -> None:
        """The averaged actor (`actor_average_tau`) moves towards the actor, after its update."""
        if self.actor_average is not None:
            torch._foreach_lerp_(
                list(self.actor_average.parameters()),
                list(self.actor.parameters()),
                self.config.actor_average_tau,
            )

    def state_dict(self) -> dict[str, Any]:
        state = {
            "actor": self.actor.state_dict(),
            "critics": self.critics.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critics_target": self.critics_target.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
            "gen": self.gen.get_state(),
            "log_alpha": self.log_alpha.detach().clone(),
            "alpha_opt": self.alpha_opt.state_dict(),
        }
        if self.actor_average is not None:
            state["actor_average"] = self.actor_average.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critics.load_state_dict(state["critics"])
        self.actor_target.load_state_dict(state["actor_target"])
        self.critics_target.load_state_dict(state["critics_target"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = int(state["updates"])
        self.gen.set_state(state["gen"])
        if "log_alpha" in state:  # checkpoints before SAC have none (and need none)
            with torch.no_grad():
                self.log_alpha.copy_(state["log_alpha"])
            self.alpha_opt.load_state_dict(state["alpha_opt"])
        if self.actor_average is not None:
            self.actor_average.load_state_dict(state["actor_average"])
