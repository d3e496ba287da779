"""DDPG as the paper states it, CleanRL style, with our improvements as named options.

Read top to bottom: the hyperparameters (one dataclass), the networks, the exploration noise,
the replay buffer, one gradient update, the training loop, the evaluation. `DDPGConfig.paper()`
is the paper's setup; `DDPGConfig.ours()` is what the shipped policy used (docs/training.md).

Speed (tools/bench_train.py): one torch thread, a numpy replay buffer, fused Adam, foreach lerp for
the target networks, N environments stepped per round of updates, larger batches.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from policy.batched import Expert, eval_envs, evaluate_batched
from policy.env import EnvConfig, ReachAlphaEnv, RewardConfig, RewardMode
from policy.expert import PDExpert
from policy.observation import ObservationConfig
from protocol.alpha5 import DEFAULT_CURRENT_LIMITS_MA, N_JOINTS

#: seeds: env i's first episode `seed * ENV_SEED_STRIDE + i + STEP_SEED_FACTOR * env_steps`;
#: demonstration episode k `seed * ENV_SEED_STRIDE + DEMO_SEED_OFFSET + k`
ENV_SEED_STRIDE = 1_000
STEP_SEED_FACTOR = 7
DEMO_SEED_OFFSET = 500_000
#: checkpoint evaluation sets, seeded from `eval_seed` plus these
WEAK_EVAL_SEED_OFFSET = 5_000
WIDE_EVAL_SEED_OFFSET = 7_000
WEAK_EVAL_TORQUE_SCALE = (0.25, 1.0, 1.0, 1.0)  # E at 25 %: the paper's scenario 3
MIN_SIDE_EVAL_EPISODES = 4
#: the weak and wide sets add reached fraction x this, minus overshoot (%) x the other
SIDE_REACHED_WEIGHT = 0.5
SIDE_OVERSHOOT_WEIGHT = 0.005
#: rad: the curriculum's widest step (E's workspace span, 5.8 - 0.4)
CURRICULUM_MAX_STEP = 5.4

# ---------------------------------------------------------------------------------------------
# Hyperparameters
# ---------------------------------------------------------------------------------------------


@dataclass
class DDPGConfig:
    """Every hyperparameter of a run. Defaults are the paper's (Carlucho et al. 2020)."""

    name: str = "paper"
    seed: int = 0
    env: EnvConfig = field(default_factory=EnvConfig)
    total_steps: int = 800_000  # env steps: 2000 episodes x 400 steps of 20 s at 20 Hz
    hidden: tuple[int, int] = (400, 300)
    actor_lr: float = 1e-4
    critic_lr: float = 1e-3
    lr_decay: float = 0.96  # multiplied in every `lr_decay_every` env steps
    lr_decay_every: int = 100_000
    batch_size: int = 64
    tau: float = 0.001
    gamma: float = 0.99
    buffer_size: int = 1_000_000
    learning_starts: int = 1_000  # env steps before the first update
    # exploration: u = pi(x) + eps * OU, eps linear from eps_start to eps_end over eps_steps
    ou_theta: float = 0.15
    ou_sigma: float = 0.2
    eps_start: float = 1.0
    eps_end: float = 0.1
    eps_steps: int | None = None  # None: the whole run
    # throughput: N envs stepped per round, `updates_per_round` gradient updates per round
    num_envs: int = 1
    updates_per_round: int = 1
    # --- improvements (all off in the paper's configuration) ---
    twin_critics: bool = False  # TD3: min of two critics in the target
    target_noise: float = 0.0  # TD3 target policy smoothing (std of the noise on a')
    target_noise_clip: float = 0.5
    policy_delay: int = 1  # TD3: actor and targets updated every `policy_delay` updates
    # demonstrations (DDPGfD / TD3+BC): expert transitions kept in their own buffer and a
    # behaviour-cloning term towards the expert's action, weight decaying to bc_weight_final
    demo_episodes: int = 0
    demo_fraction: float = 0.0  # share of each batch drawn from the demonstrations
    bc_weight: float = 0.0
    bc_weight_final: float = 0.0
    bc_decay_steps: int = 1
    #: > 0: BC error divided by (|expert action| + bc_relative): precise small commands near
    #: the target weigh as much as the saturated ones far from it
    bc_relative: float = 0.0
    q_weight: float = 1.0  # weight of the (scale-free) Q term when BC is on
    #: the demonstrator's energy weight (`PDExpert.energy_lambda`); None: the plain PD
    expert_energy_lambda: float | None = None
    #: start the actor (and its target) from these weights (.npz, the shipped format):
    #: fine-tuning a shipped policy towards a new demonstrator or reward
    init_actor: str | None = None
    # curriculum: goals at most `curriculum_start` rad away, widening to the whole workspace
    curriculum_start: float | None = None
    curriculum_steps: int = 1
    # evaluation during training
    eval_every: int = 50_000
    eval_episodes: int = 20
    eval_seed: int = 10_000
    #: subtracted from the evaluation score per joule of mean episode energy (0: ignored)
    score_energy_weight: float = 0.0

    @classmethod
    def paper(cls, **overrides: Any) -> DDPGConfig:
        return dataclasses.replace(cls(), **overrides)

    @classmethod
    def ours(cls, **overrides: Any) -> DDPGConfig:
        """TD3-style critics, shaped reward, error features, demonstrations with decaying BC."""
        env = EnvConfig(
            observation=ObservationConfig(),
            reward=RewardConfig(
                mode=RewardMode.SHAPED,
                distance_weight=2.0,
                near_scale=0.05,
                velocity_weight=0.5,
                action_change_weight=0.1,
            ),
            sensor_noise=True,
            torque_scale_low=(0.25, 1.0, 1.0, 1.0),
            param_perturbation=0.1,
        )
        base = cls(
            name="ours",
            env=env,
            total_steps=2_000_000,
            tau=0.005,
            twin_critics=True,
            target_noise=0.1,
            policy_delay=2,
            actor_lr=3e-4,
            batch_size=256,
            num_envs=8,
            updates_per_round=2,
            learning_starts=10_000,
            ou_sigma=0.2,
            eps_start=0.3,
            eps_end=0.05,
            eps_steps=200_000,
            demo_episodes=100,
            demo_fraction=0.25,
            bc_weight=1.0,
            bc_weight_final=0.1,
            bc_relative=0.1,
            eval_every=25_000,
            bc_decay_steps=1_000_000,
        )
        return dataclasses.replace(base, **overrides)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> DDPGConfig:
        presets: dict[str, Callable[..., DDPGConfig]] = {"paper": cls.paper, "ours": cls.ours}
        if name not in presets:
            raise ValueError(f"unknown config {name!r}; choose from {sorted(presets)}")
        return presets[name](**overrides)

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["env"] = self.env.to_dict()
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DDPGConfig:
        data = dict(data)
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown DDPG config keys: {sorted(unknown)}")
        data["env"] = EnvConfig.from_dict(data.get("env", {}))
        if "hidden" in data:
            data["hidden"] = tuple(data["hidden"])
        return cls(**data)


# ---------------------------------------------------------------------------------------------
# Networks: 400-300 LeakyReLU, tanh on the actor's output
# ---------------------------------------------------------------------------------------------


class Actor(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, int]) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim, hidden[0]),
            nn.LeakyReLU(),
            nn.Linear(hidden[0], hidden[1]),
            nn.LeakyReLU(),
            nn.Linear(hidden[1], act_dim),
            nn.Tanh(),
        )

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.net(obs)
        return out


class Critic(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, int]) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(obs_dim + act_dim, hidden[0]),
            nn.LeakyReLU(),
            nn.Linear(hidden[0], hidden[1]),
            nn.LeakyReLU(),
            nn.Linear(hidden[1], 1),
        )

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.net(torch.cat([obs, act], dim=1))
        return out


def actor_state_to_numpy(actor: Actor) -> dict[str, np.ndarray]:
    """Weights as plain arrays (W0 b0 W1 b1 W2 b2) for the numpy controller."""
    linears = [m for m in actor.net if isinstance(m, nn.Linear)]
    out: dict[str, np.ndarray] = {}
    for i, layer in enumerate(linears):
        out[f"W{i}"] = layer.weight.detach().cpu().numpy().astype(np.float64)
        out[f"b{i}"] = layer.bias.detach().cpu().numpy().astype(np.float64)
    return out


# ---------------------------------------------------------------------------------------------
# Exploration noise (Ornstein-Uhlenbeck, one process per env and joint)
# ---------------------------------------------------------------------------------------------


class OUNoise:
    def __init__(
        self, shape: tuple[int, ...], theta: float, sigma: float, rng: np.random.Generator
    ) -> None:
        self.theta, self.sigma, self.rng = theta, sigma, rng
        self.state = np.zeros(shape)

    def reset(self, index: int | None = None) -> None:
        if index is None:
            self.state[:] = 0.0
        else:
            self.state[index] = 0.0

    def sample(self) -> np.ndarray:
        self.state += -self.theta * self.state + self.sigma * self.rng.standard_normal(
            self.state.shape
        )
        return self.state.copy()


# ---------------------------------------------------------------------------------------------
# Replay buffer (numpy ring; also stores the expert's action for every state, for BC)
# ---------------------------------------------------------------------------------------------


class ReplayBuffer:
    FIELDS = ("obs", "act", "rew", "next_obs", "term", "expert")

    def __init__(self, capacity: int, obs_dim: int, act_dim: int) -> None:
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.act = np.zeros((capacity, act_dim), np.float32)
        self.rew = np.zeros((capacity, 1), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.term = np.zeros((capacity, 1), np.float32)
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
        term: np.ndarray,
        expert: np.ndarray,
    ) -> None:
        """Add a batch of transitions (first axis = env)."""
        n = len(obs)
        idx = (self.pos + np.arange(n)) % self.capacity
        self.obs[idx] = obs
        self.act[idx] = act
        self.rew[idx, 0] = rew
        self.next_obs[idx] = next_obs
        self.term[idx, 0] = term
        self.expert[idx] = expert
        self.full = self.full or self.pos + n >= self.capacity
        self.pos = int((self.pos + n) % self.capacity)

    def sample(self, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        idx = rng.integers(0, len(self), size=n)
        return {name: getattr(self, name)[idx] for name in self.FIELDS}

    def state(self) -> dict[str, np.ndarray]:
        size = len(self)
        data = {name: getattr(self, name)[:size] for name in self.FIELDS}
        data["meta"] = np.array([self.pos, int(self.full), self.capacity])
        return data

    def load(self, data: dict[str, np.ndarray]) -> None:
        pos, full, capacity = (int(x) for x in data["meta"])
        if capacity != self.capacity:
            raise ValueError(f"buffer capacity {capacity} in checkpoint, {self.capacity} now")
        size = len(data["obs"])
        for name in self.FIELDS:
            getattr(self, name)[:size] = data[name]
        self.pos, self.full = pos, bool(full)


# ---------------------------------------------------------------------------------------------
# The agent: networks, targets, optimisers and one gradient update
# ---------------------------------------------------------------------------------------------


def _adam(params: Any, lr: float) -> torch.optim.Adam:
    try:
        return torch.optim.Adam(params, lr=lr, fused=True)
    except (RuntimeError, TypeError):
        return torch.optim.Adam(params, lr=lr)


class Agent:
    def __init__(self, config: DDPGConfig, obs_dim: int, act_dim: int = N_JOINTS) -> None:
        self.config = config
        torch.manual_seed(config.seed)
        self.actor = Actor(obs_dim, act_dim, config.hidden)
        n_critics = 2 if config.twin_critics else 1
        self.critics = nn.ModuleList(
            Critic(obs_dim, act_dim, config.hidden) for _ in range(n_critics)
        )
        self.actor_target = copy.deepcopy(self.actor)
        self.critics_target = copy.deepcopy(self.critics)
        for p in [*self.actor_target.parameters(), *self.critics_target.parameters()]:
            p.requires_grad_(False)
        self.actor_opt = _adam(self.actor.parameters(), config.actor_lr)
        self.critic_opt = _adam(self.critics.parameters(), config.critic_lr)
        self.updates = 0
        self.gen = torch.Generator().manual_seed(config.seed + 1)

    def load_actor_npz(self, path: str | Path) -> None:
        """Actor and target actor from shipped-format weights (W0 b0 W1 b1 W2 b2)."""
        with np.load(path) as data:
            arrays = {k: data[k] for k in data.files}
        linears = [m for m in self.actor.net if isinstance(m, nn.Linear)]
        for i, layer in enumerate(linears):
            w, b = arrays.get(f"W{i}"), arrays.get(f"b{i}")
            if (
                w is None
                or b is None
                or w.shape != tuple(layer.weight.shape)
                or b.shape != tuple(layer.bias.shape)
            ):
                raise ValueError(
                    f"{path}: layer {i} does not fit a {self.config.hidden} actor "
                    f"with {linears[0].in_features} inputs"
                )
            with torch.no_grad():
                layer.weight.copy_(torch.from_numpy(w))
                layer.bias.copy_(torch.from_numpy(b))
        self.actor_target.load_state_dict(self.actor.state_dict())

    def set_learning_rates(self, env_steps: int) -> None:
        decay = self.config.lr_decay ** (env_steps // self.config.lr_decay_every)
        for group in self.actor_opt.param_groups:
            group["lr"] = self.config.actor_lr * decay
        for group in self.critic_opt.param_groups:
            group["lr"] = self.config.critic_lr * decay

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> np.ndarray:
        out: np.ndarray = self.actor(torch.from_numpy(obs)).numpy()
        return out

    def update(self, batch: dict[str, np.ndarray], bc_weight: float) -> dict[str, float]:
        cfg = self.config
        obs = torch.from_numpy(batch["obs"])
        act = torch.from_numpy(batch["act"])
        rew = torch.from_numpy(batch["rew"])
        next_obs = torch.from_numpy(batch["next_obs"])
        term = torch.from_numpy(batch["term"])

        with torch.no_grad():
            next_act = self.actor_target(next_obs)
            if cfg.target_noise > 0:
                noise = torch.randn(next_act.shape, generator=self.gen) * cfg.target_noise
                noise = noise.clamp(-cfg.target_noise_clip, cfg.target_noise_clip)
                next_act = (next_act + noise).clamp(-1.0, 1.0)
            q_next = torch.min(
                torch.stack([c(next_obs, next_act) for c in self.critics_target]), dim=0
            ).values
            target = rew + cfg.gamma * (1.0 - term) * q_next
        qs = [c(obs, act) for c in self.critics]
        critic_loss = sum(((q - target) ** 2).mean() for q in qs)
        assert isinstance(critic_loss, torch.Tensor)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        info = {"critic_loss": float(critic_loss.detach()), "q": float(qs[0].detach().mean())}

        if self.updates % cfg.policy_delay == 0:
            pi = self.actor(obs)
            q_pi = self.critics[0](obs, pi)
            if bc_weight > 0:
                # TD3+BC: the Q term is made scale-free so bc_weight means the same all run
                lam = cfg.q_weight / q_pi.abs().mean().detach().clamp(min=1e-6)
                expert = torch.from_numpy(batch["expert"])
                diff = pi - expert
                if cfg.bc_relative > 0:
                    diff = diff / (expert.abs() + cfg.bc_relative)
                bc = (diff**2).mean()
                actor_loss = -lam * q_pi.mean() + bc_weight * bc
                info["bc_loss"] = float(bc.detach())
            else:
                actor_loss = -q_pi.mean()
            self.actor_opt.zero_grad(set_to_none=True)
            # gradients for the actor only: the critic weights need none here (saves ~1/3
            # of the critic backward pass)
            actor_loss.backward(inputs=list(self.actor.parameters()))
            self.actor_opt.step()
            info["actor_loss"] = float(actor_loss.detach())
            self._soft_update()
        return info

    @torch.no_grad()
    def _soft_update(self) -> None:
        tau = self.config.tau
        for net, target in ((self.actor, self.actor_target), (self.critics, self.critics_target)):
            torch._foreach_lerp_(list(target.parameters()), list(net.parameters()), tau)

    def state_dict(self) -> dict[str, Any]:
        return {
            "actor": self.actor.state_dict(),
            "critics": self.critics.state_dict(),
            "actor_target": self.actor_target.state_dict(),
            "critics_target": self.critics_target.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
            "gen": self.gen.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critics.load_state_dict(state["critics"])
        self.actor_target.load_state_dict(state["actor_target"])
        self.critics_target.load_state_dict(state["critics_target"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = int(state["updates"])
        self.gen.set_state(state["gen"])


# ---------------------------------------------------------------------------------------------
# Evaluation during training: policy.batched (the demonstrator a run needs here)
# ---------------------------------------------------------------------------------------------


def make_expert(config: DDPGConfig) -> Expert | None:
    """The demonstrator a run needs (None without demonstrations or BC)."""
    if config.bc_weight <= 0 and config.demo_episodes <= 0:
        return None
    return PDExpert(energy_lambda=config.expert_energy_lambda)


# ---------------------------------------------------------------------------------------------
# Training loop
# ---------------------------------------------------------------------------------------------


@dataclass
class TrainState:
    env_steps: int = 0
    episodes: int = 0
    best_score: float = -np.inf
    wall_s: float = 0.0
    history: list[dict[str, Any]] = field(default_factory=list)


class Trainer:
    """Owns envs, agent, buffers and RNGs; `run()` trains, `save()`/`load()` checkpoint."""

    def __init__(
        self,
        config: DDPGConfig,
        run_dir: str | Path,
        expert: Expert | None = None,
        arm_factory: Any = None,
        log: Callable[[str], None] = print,
    ) -> None:
        torch.set_num_threads(1)
        self.config = config
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.expert = expert
        self.arm_factory = arm_factory
        self.log = log
        if (config.bc_weight > 0 or config.demo_episodes > 0) and expert is None:
            raise ValueError("demonstrations / behaviour cloning need an expert controller")
        self.rng = np.random.default_rng(config.seed)
        self.envs = [
            ReachAlphaEnv(config.env, arm_factory=arm_factory) for _ in range(config.num_envs)
        ]
        obs_dim = self.envs[0].observation_space.shape[0]  # type: ignore[index]
        self.obs_dim = obs_dim
        self.agent = Agent(config, obs_dim)
        if config.init_actor is not None:
            self.agent.load_actor_npz(config.init_actor)
        self.buffer = ReplayBuffer(config.buffer_size, obs_dim, N_JOINTS)
        self.demos = ReplayBuffer(
            max(1, config.demo_episodes * config.env.steps_per_episode), obs_dim, N_JOINTS
        )
        self.noise = OUNoise(
            (config.num_envs, N_JOINTS), config.ou_theta, config.ou_sigma, self.rng
        )
        # built once: arms load the MJCF when constructed, so evaluation uses the same model
        self.eval_nominal = eval_envs(config.env, config.eval_episodes, None, arm_factory)
        self.eval_weak = eval_envs(
            config.env,
            max(MIN_SIDE_EVAL_EPISODES, config.eval_episodes // 2),
            WEAK_EVAL_TORQUE_SCALE,
            arm_factory,
        )
        # a run on a wider workspace is also scored on episodes from it (e.g. B up to the
        # paper's scenario angles), so the best actor is not chosen on the narrow range alone
        wide = config.env.workspace_low is not None or config.env.workspace_high is not None
        self.eval_wide = (
            eval_envs(
                config.env,
                max(MIN_SIDE_EVAL_EPISODES, config.eval_episodes // 2),
                None,
                arm_factory,
                training_workspace=True,
            )
            if wide
            else []
        )
        self.state = TrainState()
        self.best_actor = copy.deepcopy(self.agent.actor.state_dict())
        self._obs: np.ndarray | None = None

    # -- schedules -------------------------------------------------------------------------
    def epsilon(self) -> float:
        cfg = self.config
        horizon = cfg.eps_steps or cfg.total_steps
        frac = min(1.0, self.state.env_steps / max(1, horizon))
        return cfg.eps_start + frac * (cfg.eps_end - cfg.eps_start)

    def bc_weight(self) -> float:
        cfg = self.config
        frac = min(1.0, self.state.env_steps / max(1, cfg.bc_decay_steps))
        return cfg.bc_weight + frac * (cfg.bc_weight_final - cfg.bc_weight)

    def _episode_config(self) -> EnvConfig:
        cfg = self.config
        if cfg.curriculum_start is None:
            return cfg.env
        frac = min(1.0, self.state.env_steps / max(1, cfg.curriculum_steps))
        if frac >= 1.0:
            return cfg.env
        return dataclasses.replace(
            cfg.env,
            max_step=cfg.curriculum_start + frac * (CURRICULUM_MAX_STEP - cfg.curriculum_start),
        )

    def _reset_env(self, i: int) -> np.ndarray:
        env = self.envs[i]
        env.config = self._episode_config()
        seed = None
        if self.state.episodes < self.config.num_envs:  # first episode of each env: seed it
            seed = self.config.seed * ENV_SEED_STRIDE + i + STEP_SEED_FACTOR * self.state.env_steps
        obs, _ = env.reset(seed=seed)
        self.noise.reset(i)
        self.state.episodes += 1
        return obs

    def _expert_actions(self) -> np.ndarray:
        if self.expert is None:
            return np.zeros((len(self.envs), N_JOINTS), np.float32)
        return np.stack([self.expert(env) for env in self.envs]).astype(np.float32)

    # -- demonstrations --------------------------------------------------------------------
    def collect_demonstrations(self) -> None:
        cfg = self.config
        if cfg.demo_episodes <= 0 or self.expert is None:
            return
        env = ReachAlphaEnv(cfg.env, arm_factory=self.arm_factory)
        for ep in range(cfg.demo_episodes):
            obs, _ = env.reset(seed=cfg.seed * ENV_SEED_STRIDE + DEMO_SEED_OFFSET + ep)
            done = False
            while not done:
                a = self.expert(env).astype(np.float32)
                next_obs, r, term, trunc, _ = env.step(a)
                self.demos.add(
                    obs[None],
                    a[None],
                    np.array([r]),
                    next_obs[None],
                    np.array([float(term)]),
                    a[None],
                )
                obs, done = next_obs, term or trunc
        self.log(f"collected {len(self.demos)} demonstration transitions")

    # -- main loop -------------------------------------------------------------------------
    def run(
        self,
        until_steps: int | None = None,
        checkpoint_every_s: float = 600.0,
        progress: Callable[[TrainState, dict[str, float]], None] | None = None,
        csv_path: Path | None = None,
    ) -> TrainState:
        cfg = self.config
        until = min(until_steps or cfg.total_steps, cfg.total_steps)
        if self.state.env_steps == 0 and len(self.demos) == 0:
            self.collect_demonstrations()
        if self._obs is None:
            self._obs = np.stack([self._reset_env(i) for i in range(cfg.num_envs)])
        ep_returns = np.zeros(cfg.num_envs)
        csv = open(csv_path, "a", buffering=1) if csv_path else None  # noqa: SIM115
        if csv is not None and csv.tell() == 0:
            csv.write(
                "env_steps,episodes,wall_s,episode_return,critic_loss,actor_loss,"
                "bc_loss,q,epsilon,bc_weight\n"
            )
        t_last_ckpt = time.monotonic()
        t_start = time.monotonic() - self.state.wall_s
        next_eval = (self.state.env_steps // cfg.eval_every + 1) * cfg.eval_every
        losses: dict[str, float] = {}
        try:
            while self.state.env_steps < until:
                obs = self._obs
                expert_a = self._expert_actions()
                if self.state.env_steps < cfg.learning_starts and self.expert is None:
                    actions = self.rng.uniform(-1, 1, size=(cfg.num_envs, N_JOINTS))
                else:
                    actions = self.agent.act(obs) + self.epsilon() * self.noise.sample()
                actions = np.clip(actions, -1.0, 1.0).astype(np.float32)
                next_obs = np.empty_like(obs)
                rewards = np.empty(cfg.num_envs)
                terms = np.zeros(cfg.num_envs)
                done = np.zeros(cfg.num_envs, dtype=bool)
                for i, env in enumerate(self.envs):
                    o, r, term, trunc, _ = env.step(actions[i])
                    next_obs[i], rewards[i], terms[i], done[i] = o, r, float(term), term or trunc
                # truncation (the 20 s limit) still bootstraps: only `term` cuts the target
                self.buffer.add(obs, actions, rewards, next_obs, terms, expert_a)
                ep_returns += rewards
                for j in np.nonzero(done)[0]:
                    if csv is not None:
                        csv.write(self._csv_row(ep_returns[j], losses))
                    ep_returns[j] = 0.0
                    next_obs[j] = self._reset_env(int(j))
                self._obs = next_obs
                self.state.env_steps += cfg.num_envs

                if self.state.env_steps >= cfg.learning_starts:
                    self.agent.set_learning_rates(self.state.env_steps)
                    for _ in range(cfg.updates_per_round):
                        losses = self.agent.update(self._sample(), self.bc_weight())
                self.state.wall_s = time.monotonic() - t_start
                if progress is not None:
                    progress(self.state, losses)
                if self.state.env_steps >= next_eval:
                    next_eval += cfg.eval_every
                    self.evaluate_and_keep_best()
                if time.monotonic() - t_last_ckpt > checkpoint_every_s:
                    self.save()
                    t_last_ckpt = time.monotonic()
        finally:
            if csv is not None:
                csv.close()
        return self.state

    def _sample(self) -> dict[str, np.ndarray]:
        cfg = self.config
        n_demo = int(round(cfg.batch_size * cfg.demo_fraction)) if len(self.demos) else 0
        batch = self.buffer.sample(cfg.batch_size - n_demo, self.rng)
        if n_demo:
            demo = self.demos.sample(n_demo, self.rng)
            batch = {k: np.concatenate([batch[k], demo[k]]) for k in batch}
        return batch

    def _csv_row(self, ep_return: float, losses: dict[str, float]) -> str:
        s = self.state
        fields = [
            s.env_steps,
            s.episodes,
            f"{s.wall_s:.1f}",
            f"{ep_return:.3f}",
            f"{losses.get('critic_loss', float('nan')):.5g}",
            f"{losses.get('actor_loss', float('nan')):.5g}",
            f"{losses.get('bc_loss', float('nan')):.5g}",
            f"{losses.get('q', float('nan')):.5g}",
            f"{self.epsilon():.4f}",
            f"{self.bc_weight():.4f}",
        ]
        return ",".join(str(f) for f in fields) + "\n"

    def evaluate_and_keep_best(self) -> dict[str, Any]:
        cfg = self.config
        nominal = evaluate_batched(
            self.agent.act, cfg.env, cfg.eval_episodes, cfg.eval_seed, envs=self.eval_nominal
        )
        weak = evaluate_batched(
            self.agent.act,
            cfg.env,
            len(self.eval_weak),
            cfg.eval_seed + WEAK_EVAL_SEED_OFFSET,
            envs=self.eval_weak,
        )
        score = (
            nominal.score(cfg.score_energy_weight)
            + SIDE_REACHED_WEIGHT * weak.reached_fraction
            - SIDE_OVERSHOOT_WEIGHT * weak.overshoot_pct
        )
        record: dict[str, Any] = {
            "env_steps": self.state.env_steps,
            "wall_s": round(self.state.wall_s, 1),
            "score": score,
            "nominal": nominal.to_dict(),
            "torque_e_25pct": weak.to_dict(),
        }
        wide_note = ""
        if self.eval_wide:
            wide = evaluate_batched(
                self.agent.act,
                cfg.env,
                len(self.eval_wide),
                cfg.eval_seed + WIDE_EVAL_SEED_OFFSET,
                envs=self.eval_wide,
            )
            score += (
                SIDE_REACHED_WEIGHT * wide.reached_fraction
                - SIDE_OVERSHOOT_WEIGHT * wide.overshoot_pct
            )
            record["score"] = score
            record["training_workspace"] = wide.to_dict()
            wide_note = (
                f" | wide: reached {wide.reached_fraction:.2f} "
                f"final {wide.final_error:.4f} OS {wide.overshoot_pct:.2f}%"
            )
        self.state.history.append(record)
        if score > self.state.best_score:
            self.state.best_score = score
            self.best_actor = copy.deepcopy(self.agent.actor.state_dict())
            record["best"] = True
            self.export_best(self.run_dir / "best_actor.npz", record)
        with open(self.run_dir / "eval.jsonl", "a") as fh:
            fh.write(json.dumps(record) + "\n")
        self.log(
            f"eval @ {self.state.env_steps}: reached {nominal.reached_fraction:.2f} "
            f"final {nominal.final_error:.4f} rmse x{nominal.rmse_floor_ratio:.2f} "
            f"OS {nominal.overshoot_pct:.2f}% ST {nominal.settling_s:.2f}s "
            f"SS {nominal.steady_error:.4f} MIE {nominal.mie:.3f} E {nominal.energy_j:.2f}J "
            f"| E25%: reached {weak.reached_fraction:.2f} "
            f"OS {weak.overshoot_pct:.2f}%{wide_note}" + (" *best*" if record.get("best") else "")
        )
        return record

    def export_best(self, path: Path, record: dict[str, Any]) -> None:
        actor = Actor(self.obs_dim, N_JOINTS, self.config.hidden)
        actor.load_state_dict(self.best_actor)
        save_actor_npz(
            path,
            actor,
            self.config,
            extra={"eval": record, "env_steps": self.state.env_steps, "wall_s": self.state.wall_s},
        )

    # -- checkpoints -----------------------------------------------------------------------
    def save(self) -> Path:
        """Checkpoint of everything needed to continue (episodes restart on resume).

        The buffer goes to a file named by the step, then checkpoint.pt (naming that file)
        replaces the old one atomically, then older buffers are removed: a kill at any
        moment leaves a consistent pair.
        """
        path = self.run_dir / "checkpoint.pt"
        buffer_name = f"buffer-{self.state.env_steps}.npz"
        arrays: dict[str, Any] = {
            **self.buffer.state(),
            **{f"demo_{k}": v for k, v in self.demos.state().items()},
            "env_steps": np.array(self.state.env_steps),
        }
        np.savez(self.run_dir / "buffer.tmp.npz", **arrays)
        os.replace(self.run_dir / "buffer.tmp.npz", self.run_dir / buffer_name)
        tmp = path.with_suffix(".tmp")
        torch.save(
            {
                "config": self.config.to_dict(),
                "agent": self.agent.state_dict(),
                "best_actor": self.best_actor,
                "state": dataclasses.asdict(self.state),
                "rng": self.rng.bit_generator.state,
                "torch_rng": torch.get_rng_state(),
                "buffer_file": buffer_name,
            },
            tmp,
        )
        os.replace(tmp, path)
        for old in self.run_dir.glob("buffer*.npz"):
            if old.name != buffer_name:
                old.unlink()
        return path

    def load(self) -> None:
        ckpt = torch.load(self.run_dir / "checkpoint.pt", weights_only=False)
        saved = DDPGConfig.from_dict(ckpt["config"])
        if saved.to_dict() != {**self.config.to_dict(), "total_steps": saved.total_steps}:
            raise ValueError(
                "checkpoint was made with a different configuration; "
                "resume with the same --config and options"
            )
        self.agent.load_state_dict(ckpt["agent"])
        self.best_actor = ckpt["best_actor"]
        self.state = TrainState(**ckpt["state"])
        self.rng.bit_generator.state = ckpt["rng"]
        torch.set_rng_state(ckpt["torch_rng"])
        with np.load(self.run_dir / ckpt.get("buffer_file", "buffer.npz")) as data:
            # the two files are replaced one after the other: a kill in between is detected
            saved_at = int(data["env_steps"]) if "env_steps" in data.files else None
            if saved_at is not None and saved_at != self.state.env_steps:
                raise ValueError(
                    f"buffer.npz is from step {saved_at}, checkpoint.pt from "
                    f"{self.state.env_steps}: the last save was interrupted"
                )
            self.buffer.load({k: data[k] for k in (*ReplayBuffer.FIELDS, "meta")})
            self.demos.load({k: data[f"demo_{k}"] for k in (*ReplayBuffer.FIELDS, "meta")})
        self._obs = None  # episodes restart after a resume
        # later episodes are drawn from each env's own generator: reseed them from the step
        for i, env in enumerate(self.envs):
            env.reset(
                seed=self.config.seed * ENV_SEED_STRIDE
                + i
                + STEP_SEED_FACTOR * self.state.env_steps
            )


def save_actor_npz(
    path: str | Path, actor: Actor, config: DDPGConfig, extra: dict[str, Any] | None = None
) -> None:
    """Weights (npz) plus what the controller needs to rebuild inputs and outputs (json)."""
    path = Path(path)
    arrays: dict[str, Any] = dict(actor_state_to_numpy(actor))
    meta = {
        "format": "reach-stack ddpg actor v1",
        "layers": ["linear", "leaky_relu", "linear", "leaky_relu", "linear", "tanh"],
        "leaky_relu_slope": 0.01,
        "current_limits_mA": list(DEFAULT_CURRENT_LIMITS_MA),
        "observation": config.env.observation.to_dict(),
        "env": config.env.to_dict(),
        "config": config.to_dict(),
        **(extra or {}),
    }
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1, default=_json_default))


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Enum):
        return obj.value
    raise TypeError(f"not JSON serialisable: {type(obj)}")
