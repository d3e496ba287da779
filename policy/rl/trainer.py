"""Training: the loop that steps the envs, fills the buffers and updates the agent, the
checkpoint evaluation that keeps the best actor, and checkpoints that survive a kill.

`Trainer` owns everything a run needs (envs, agent, buffers, generators); `TrainState` is what
it has done so far. A run directory holds eval.jsonl, best_actor.npz/.json
(policy.controllers.weights; best_online_actor.npz/.json beside it with `actor_average_tau`),
every checkpoint's actor in checkpoint-actors/, checkpoint.pt and buffer-STEP.npz; a sitting
of tools/train.py (policy.rl.session) adds config.json, train.csv and the logs.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch

from policy.controllers.weights import CHECKPOINT_ACTORS, CheckpointActor, TrainingStage
from policy.rl.agent import Agent
from policy.rl.batched import EvalResult, Expert, eval_envs, evaluate_batched
from policy.rl.checkpoint import save_actor_npz
from policy.rl.collector import CollectorProcess
from policy.rl.config import (
    CURRICULUM_MAX_STEP,
    DEMO_SEED_OFFSET,
    ENV_SEED_STRIDE,
    ENVELOPE_EVAL_SEED_OFFSET,
    ENVELOPE_REACHED_WEIGHT,
    MIN_SIDE_EVAL_EPISODES,
    SIDE_OVERSHOOT_WEIGHT,
    SIDE_REACHED_WEIGHT,
    STEP_SEED_FACTOR,
    WEAK_EVAL_SEED_OFFSET,
    WIDE_EVAL_SEED_OFFSET,
    Algorithm,
    DDPGConfig,
    weak_eval_torque_scale,
)
from policy.rl.env import EnvConfig, ReachAlphaEnv, time_limited
from policy.rl.expert import PDExpert
from policy.rl.exploration import OUNoise
from policy.rl.networks import Actor, GaussianActor
from policy.rl.nstep import NStepReturns
from policy.rl.relabel import GoalRelabeller, Relabelled
from policy.rl.replay import ReplayBuffer


def _side_score(result: EvalResult, reached_weight: float) -> float:
    """What a side set adds to the checkpoint score: reaching, less its overshoot."""
    return reached_weight * result.reached_fraction - SIDE_OVERSHOOT_WEIGHT * result.overshoot_pct


def _open_csv(path: Path | None) -> TextIO | None:
    """train.csv for appending (one row per finished episode), its header if it is new."""
    if path is None:
        return None
    csv = open(path, "a", buffering=1)  # noqa: SIM115
    if csv.tell() == 0:
        csv.write(
            "env_steps,episodes,wall_s,episode_return,critic_loss,actor_loss,"
            "bc_loss,q,epsilon,bc_weight\n"
        )
    return csv


def make_expert(config: DDPGConfig) -> Expert | None:
    """The demonstrator a run needs (None without demonstrations or BC)."""
    if config.bc_weight <= 0 and config.demo_episodes <= 0:
        return None
    gains: dict[str, Any] = {}
    if config.expert_kp is not None:
        gains["kp"] = config.expert_kp
    if config.expert_kd is not None:
        gains["kd"] = config.expert_kd
    return PDExpert(energy_lambda=config.expert_energy_lambda, **gains)


@dataclass
class _Cadence:
    """When a run's loop evaluates and checkpoints next, and its clock's origin."""

    t_start: float
    next_eval: int
    last_checkpoint: float
    checkpoint_every_s: float


@dataclass
class TrainState:
    """What a run has done: saved in its checkpoint, so a resumed run goes on from here."""

    env_steps: int = 0
    episodes: int = 0
    best_score: float = -np.inf
    #: the online actor's best score, with `actor_average_tau` (best_online_actor.npz)
    best_online_score: float = -np.inf
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
        command: str = "",
    ) -> None:
        torch.set_num_threads(1)
        self.config = config
        #: how the run was started (and resumed), recorded in each exported actor's provenance
        self.command = command
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.expert = expert
        self.arm_factory = arm_factory
        self.log = log
        #: called with (episodes done, episodes to do) after each demonstration episode
        self.demo_progress: Callable[[int, int], None] | None = None
        if (config.bc_weight > 0 or config.demo_episodes > 0) and expert is None:
            raise ValueError("demonstrations / behaviour cloning need an expert controller")
        self.rng = np.random.default_rng(config.seed)
        #: the envs themselves (the expert and the curriculum read and set their state) ...
        #: (none here with `collector_process`: the child process steps its own)
        self.envs = [
            ReachAlphaEnv(config.env, arm_factory=arm_factory)
            for _ in range(0 if config.collector_process else config.num_envs)
        ]
        #: ... and behind gymnasium's TimeLimit, as gym.make builds them: episodes are
        #: stepped and reset here, and end (truncated) after `config.env.episode_s`
        self.timed = [time_limited(env) for env in self.envs]
        #: the arm's joints: the actor's outputs
        self.n_joints = n = config.env.model.n_joints
        obs_dim = config.env.observation.size_for(n)
        self.obs_dim = obs_dim
        self.agent = Agent(config, obs_dim, n)
        if config.init_actor is not None:
            self.agent.load_actor_npz(config.init_actor)
        self.buffer = ReplayBuffer(config.buffer_size, obs_dim, n)
        self.demos = ReplayBuffer(
            max(1, config.demo_episodes * config.env.steps_per_episode), obs_dim, n
        )
        self.noise = OUNoise((config.num_envs, n), config.ou_theta, config.ou_sigma, self.rng)
        #: the envs' steps become n-step transitions here, whichever process stepped them
        self.nstep = NStepReturns(config.num_envs, config.n_step, config.gamma)
        #: goal relabelling of the envs here (`her_goals`; the collector has its own)
        self.relabeller = GoalRelabeller(
            self.envs, config.her_goals, np.random.default_rng([config.seed, 2])
        )
        # built once: arms load the MJCF when constructed, so evaluation uses the same model
        self.eval_nominal = eval_envs(config.env, config.eval_episodes, None, arm_factory)
        self.eval_weak = eval_envs(
            config.env,
            max(MIN_SIDE_EVAL_EPISODES, config.eval_episodes // 2),
            weak_eval_torque_scale(n),
            arm_factory,
        )
        #: the weak set's joint (the base joint at 25 %: E on the Alpha 5)
        self.weak_joint = config.env.model.joint_letters[0]
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
        #: fixed arms of the uncertainty envelope (one per episode, fixed by its seed): the
        #: screen that keeps an actor that chatters on a latent arm from being the best
        self.eval_envelope = (
            eval_envs(config.env, config.eval_envelope_episodes, None, arm_factory, envelope=True)
            if config.eval_envelope_episodes > 0
            else []
        )
        self.state = TrainState()
        self.best_actor = copy.deepcopy(self.agent.actor.state_dict())
        self._obs: np.ndarray | None = None
        #: the envs' child process with `collector_process` (started by the first `run`)
        self._collector: CollectorProcess | None = None

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
        self.envs[i].config = self._episode_config()
        seed = None
        if self.state.episodes < self.config.num_envs:  # first episode of each env: seed it
            seed = self.config.seed * ENV_SEED_STRIDE + i + STEP_SEED_FACTOR * self.state.env_steps
        obs, _ = self.timed[i].reset(seed=seed)
        self.relabeller.started(i)
        self.noise.reset(i)
        self.state.episodes += 1
        return obs

    def _expert_actions(self) -> np.ndarray:
        if self.expert is None:
            return np.zeros((len(self.envs), self.n_joints), np.float32)
        return np.stack([self._label(env) for env in self.envs]).astype(np.float32)

    def _label(self, env: ReachAlphaEnv) -> np.ndarray:
        """The expert's action for `env`'s state; NaN (no BC) where `bc_max_latency` says the
        demonstrator is no teacher."""
        assert self.expert is not None
        action = np.asarray(self.expert(env), dtype=np.float64)
        limit = self.config.bc_max_latency
        if limit is not None and env.latency_substeps > limit * env.n_substeps:
            return np.full(self.n_joints, np.nan)
        return action

    # -- demonstrations --------------------------------------------------------------------
    def collect_demonstrations(self) -> None:
        cfg = self.config
        if cfg.demo_episodes <= 0 or self.expert is None:
            return
        env = ReachAlphaEnv(cfg.env, arm_factory=self.arm_factory)
        timed = time_limited(env)
        for ep in range(cfg.demo_episodes):
            obs, _ = timed.reset(seed=cfg.seed * ENV_SEED_STRIDE + DEMO_SEED_OFFSET + ep)
            done = False
            while not done:
                a = self.expert(env).astype(np.float32)
                label = self._label(env).astype(np.float32)
                next_obs, r, term, trunc, _ = timed.step(a)
                self.demos.add(
                    obs[None],
                    a[None],
                    np.array([r]),
                    next_obs[None],
                    np.array([cfg.gamma * (1.0 - float(term))]),
                    label[None],
                )
                obs, done = next_obs, term or trunc
            if self.demo_progress is not None:
                self.demo_progress(ep + 1, cfg.demo_episodes)
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
        if cfg.collector_process:
            return self._run_pipelined(until, checkpoint_every_s, progress, csv_path)
        if self.state.env_steps == 0 and len(self.demos) == 0:
            self.collect_demonstrations()
        if self._obs is None:
            self._obs = np.stack([self._reset_env(i) for i in range(cfg.num_envs)])
            self.nstep.reset()
        ep_returns = np.zeros(cfg.num_envs)
        csv = _open_csv(csv_path)
        cadence = self._cadence(checkpoint_every_s)
        losses: dict[str, float] = {}
        try:
            while self.state.env_steps < until:
                obs = self._obs
                expert_a = self._expert_actions()
                if self.state.env_steps < cfg.learning_starts and self.expert is None:
                    actions = self.rng.uniform(-1, 1, size=(cfg.num_envs, self.n_joints))
                else:
                    actions = self._explore(obs)
                actions = np.clip(actions, -1.0, 1.0).astype(np.float32)
                next_obs = np.empty_like(obs)
                rewards = np.empty(cfg.num_envs)
                terms = np.zeros(cfg.num_envs)
                done = np.zeros(cfg.num_envs, dtype=bool)
                for i, env in enumerate(self.timed):
                    o, r, term, trunc, info = env.step(actions[i])
                    next_obs[i], rewards[i], terms[i], done[i] = o, r, float(term), term or trunc
                    self.relabeller.stepped(i, actions[i], info)
                # truncation (the 20 s limit) still bootstraps: only `term` cuts the target
                self._store(obs, actions, rewards, next_obs, terms, done, expert_a)
                ep_returns += rewards
                for j in np.nonzero(done)[0]:
                    if csv is not None:
                        csv.write(self._csv_row(ep_returns[j], losses))
                    ep_returns[j] = 0.0
                    replay = self.relabeller.finished(int(j))
                    if replay is not None:
                        self._add_relabelled(replay)
                    next_obs[j] = self._reset_env(int(j))
                self._obs = next_obs
                self.state.env_steps += cfg.num_envs
                losses = self._learn() or losses
                self._end_round(cadence, progress, losses)
        finally:
            if csv is not None:
                csv.close()
        return self.state

    def _run_pipelined(
        self,
        until: int,
        checkpoint_every_s: float,
        progress: Callable[[TrainState, dict[str, float]], None] | None,
        csv_path: Path | None,
    ) -> TrainState:
        """`run` with the envs in a child process one round ahead (policy.rl.collector):
        the learner updates on the buffer while the child steps the next round."""
        cfg = self.config
        if self.expert is not None or cfg.curriculum_start is not None:
            raise ValueError("collector_process: the expert and the curriculum need the envs here")
        if self.arm_factory is not None:
            raise ValueError("collector_process: the child builds the nominal arm only")
        csv = _open_csv(csv_path)
        cadence = self._cadence(checkpoint_every_s)
        losses: dict[str, float] = {}
        if self._collector is None:  # kept across calls: its episodes go on, as `_obs`'s
            self._collector = CollectorProcess(cfg, self.state.env_steps)
            self.nstep.reset()  # the child starts new episodes
            self.state.episodes += cfg.num_envs  # the child's first episodes
        collector = self._collector

        def ask() -> None:
            uniform = self.state.env_steps < cfg.learning_starts
            actor = None if uniform else self._actor_arrays()
            collector.request(actor, self.epsilon(), uniform)

        if self.state.env_steps < until:
            ask()
        try:
            while self.state.env_steps < until:
                losses = self._learn() or losses  # while the child steps the next round
                got = collector.result()
                no_label = np.zeros_like(got.actions)
                self._store(
                    got.obs, got.actions, got.rewards, got.next_obs, got.terms, got.dones, no_label
                )
                if got.relabelled is not None:
                    self._add_relabelled(got.relabelled)
                self.state.env_steps += cfg.num_envs
                self.state.episodes += len(got.returns)
                if self.state.env_steps < until:
                    ask()
                if csv is not None:
                    for ep_return in got.returns:
                        csv.write(self._csv_row(ep_return, losses))
                self._end_round(cadence, progress, losses)
        except BaseException:  # a round may be in flight: end the child with it
            self.close()
            raise
        finally:
            if csv is not None:
                csv.close()
        return self.state

    def _store(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        next_obs: np.ndarray,
        terms: np.ndarray,
        dones: np.ndarray,
        labels: np.ndarray,
    ) -> None:
        """A round of env steps (row i: env i) into the buffer, as n-step transitions."""
        out = self.nstep.push(obs, actions, rewards, next_obs, terms, dones)
        self.buffer.add(
            out.obs, out.actions, out.rewards, out.next_obs, out.discounts, labels[out.envs]
        )

    def _add_relabelled(self, replay: Relabelled) -> None:
        """Replayed episodes join the buffer (no expert label: the expert saw other goals)."""
        fill = np.nan if self.expert is not None else 0.0  # NaN: no BC term (`_label`)
        label = np.full_like(replay.actions, fill)
        discounts = self.config.gamma * (1.0 - replay.terms)
        self.buffer.add(
            replay.obs, replay.actions, replay.rewards, replay.next_obs, discounts, label
        )

    def _learn(self) -> dict[str, float] | None:
        """A round's gradient updates once learning has started; the last one's losses."""
        cfg = self.config
        if self.state.env_steps < cfg.learning_starts:
            return None
        self.agent.set_learning_rates(self.state.env_steps)
        losses = None
        for _ in range(cfg.updates_per_round):
            losses = self.agent.update(self._sample(), self.bc_weight())
        return losses

    def _cadence(self, checkpoint_every_s: float) -> _Cadence:
        every = self.config.eval_every
        return _Cadence(
            t_start=time.monotonic() - self.state.wall_s,
            next_eval=(self.state.env_steps // every + 1) * every,
            last_checkpoint=time.monotonic(),
            checkpoint_every_s=checkpoint_every_s,
        )

    def _end_round(
        self,
        cadence: _Cadence,
        progress: Callable[[TrainState, dict[str, float]], None] | None,
        losses: dict[str, float],
    ) -> None:
        """After each round, in either loop: the clock, progress, evaluation, checkpoint."""
        self.state.wall_s = time.monotonic() - cadence.t_start
        if progress is not None:
            progress(self.state, losses)
        if self.state.env_steps >= cadence.next_eval:
            cadence.next_eval += self.config.eval_every
            self.evaluate_and_keep_best()
        if time.monotonic() - cadence.last_checkpoint > cadence.checkpoint_every_s:
            self.save()
            cadence.last_checkpoint = time.monotonic()

    def close(self) -> None:
        """End the collector process, if `collector_process` started one."""
        if self._collector is not None:
            self._collector.close()
            self._collector = None

    def _explore(self, obs: np.ndarray) -> np.ndarray:
        """The actions the envs take once learning starts: the actor's plus eps times OU
        noise (DDPG), or samples of the Gaussian actor (SAC)."""
        if self.config.algorithm is Algorithm.SAC:
            return self.agent.explore(obs)
        return self.agent.act(obs) + self.epsilon() * self.noise.sample()

    def _actor_arrays(self) -> list[np.ndarray]:
        """The actor's layers (W, b per layer, torch's layout) for the collector; SAC's
        log-std head last."""
        actor = self.agent.actor
        layers = actor.linears()
        if isinstance(actor, GaussianActor):
            layers = [*layers, actor.log_std]
        return [t.detach().numpy().copy() for layer in layers for t in (layer.weight, layer.bias)]

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
            # SAC explores by its own samples: no eps
            "nan" if self.config.algorithm is Algorithm.SAC else f"{self.epsilon():.4f}",
            f"{self.bc_weight():.4f}",
        ]
        return ",".join(str(f) for f in fields) + "\n"

    def evaluate_and_keep_best(self) -> dict[str, Any]:
        """Score the actor that is kept (the averaged one with `actor_average_tau`) on the
        checkpoint sets, and keep it in best_actor.npz if it is the best so far; with the
        average on, the online actor is scored beside it (record["online"]) and its best
        kept in best_online_actor.npz, so one run measures what the averaging brings."""
        agent = self.agent
        averaged = agent.actor_average is not None
        record, note = self._checkpoint_record(agent.act_average if averaged else agent.act)
        score = record["score"]
        self.state.history.append(record)
        kept = agent.actor if agent.actor_average is None else agent.actor_average
        self.export_actor(self._checkpoint_actor(CheckpointActor.KEPT), record, kept.state_dict())
        if score > self.state.best_score:
            self.state.best_score = score
            self.best_actor = copy.deepcopy(kept.state_dict())
            record["best"] = True
            self.export_actor(self.run_dir / "best_actor.npz", record, self.best_actor)
        if averaged:
            online, _ = self._checkpoint_record(agent.act)
            record["online"] = online
            self.export_actor(
                self._checkpoint_actor(CheckpointActor.ONLINE), online, agent.actor.state_dict()
            )
            if online["score"] > self.state.best_online_score:
                self.state.best_online_score = online["score"]
                online["best"] = True
                self.export_actor(
                    self.run_dir / "best_online_actor.npz", online, agent.actor.state_dict()
                )
        with open(self.run_dir / "eval.jsonl", "a") as fh:
            fh.write(json.dumps(record) + "\n")
        online_note = (
            f" | online: score {record['online']['score']:.3f}"
            f" OS {record['online']['nominal']['overshoot_pct']:.2f}%"
            if averaged
            else ""
        )
        best = " *best*" if record.get("best") else ""
        self.log(f"eval @ {self.state.env_steps}: {note}{best}{online_note}")
        return record

    def _checkpoint_actor(self, kind: CheckpointActor) -> Path:
        """Where this checkpoint's `kind` actor is kept: every checkpoint's actor stays, so a
        run can be reselected later on more episodes (`policy.campaigns.reselect`)."""
        folder = self.run_dir / CHECKPOINT_ACTORS
        folder.mkdir(exist_ok=True)
        return folder / kind.file(self.state.env_steps)

    def _checkpoint_record(
        self, act: Callable[[np.ndarray], np.ndarray]
    ) -> tuple[dict[str, Any], str]:
        """One actor on every checkpoint set: its results and score, and its log line."""
        cfg = self.config
        nominal = self._side(self.eval_nominal, 0, act)
        weak = self._side(self.eval_weak, WEAK_EVAL_SEED_OFFSET, act)
        score = nominal.score(cfg.score_energy_weight) + _side_score(weak, SIDE_REACHED_WEIGHT)
        record: dict[str, Any] = {
            "env_steps": self.state.env_steps,
            "wall_s": round(self.state.wall_s, 1),
            "score": score,
            "nominal": nominal.to_dict(),
            f"torque_{self.weak_joint.lower()}_25pct": weak.to_dict(),
        }
        note = (
            f"reached {nominal.reached_fraction:.2f} "
            f"final {nominal.final_error:.4f} rmse x{nominal.rmse_floor_ratio:.2f} "
            f"OS {nominal.overshoot_pct:.2f}% ST {nominal.settling_s:.2f}s "
            f"SS {nominal.steady_error:.4f} MIE {nominal.mie:.3f} E {nominal.energy_j:.2f}J "
            f"| {self.weak_joint}25%: reached {weak.reached_fraction:.2f} "
            f"OS {weak.overshoot_pct:.2f}%"
        )
        sides = (
            ("envelope", self.eval_envelope, ENVELOPE_EVAL_SEED_OFFSET, ENVELOPE_REACHED_WEIGHT),
            ("training_workspace", self.eval_wide, WIDE_EVAL_SEED_OFFSET, SIDE_REACHED_WEIGHT),
        )
        for key, envs, offset, weight in sides:
            if not envs:
                continue
            side = self._side(envs, offset, act)
            score += _side_score(side, weight)
            record[key] = side.to_dict()
            note += (
                f" | {'wide' if key == 'training_workspace' else key}: reached "
                f"{side.reached_fraction:.3f} rest {side.at_rest_fraction:.3f} "
                f"final {side.final_error:.4f} OS {side.overshoot_pct:.2f}% "
                f"max {side.overshoot_max_pct:.1f}%"
            )
        record["score"] = score
        return record, note

    def _side(
        self,
        envs: list[ReachAlphaEnv],
        seed_offset: int,
        act: Callable[[np.ndarray], np.ndarray],
    ) -> EvalResult:
        """An actor on one fixed checkpoint set (envs from `eval_envs`)."""
        return evaluate_batched(
            act, self.config.env, len(envs), self.config.eval_seed + seed_offset, envs=envs
        )

    def export_actor(self, path: Path, record: dict[str, Any], weights: dict[str, Any]) -> None:
        actor = Actor(self.obs_dim, self.n_joints, self.config.hidden)
        # SAC's log-std head is for exploring only: what ships is the mean, an `Actor`
        actor.load_state_dict({k: v for k, v in weights.items() if k.startswith("net.")})
        stage = TrainingStage(
            run=self.run_dir.name,
            env_steps=self.state.env_steps,
            wall_s=round(self.state.wall_s, 1),
            seed=self.config.seed,
            command=self.command,
            init_actor=self.config.init_actor,
        )
        save_actor_npz(path, actor, self.config, extra={"eval": record}, stage=stage)

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
            names = (*ReplayBuffer.FIELDS, "term", "meta")
            gamma = self.config.gamma
            self.buffer.load({k: data[k] for k in names if k in data.files}, gamma)
            demo = {k: data[f"demo_{k}"] for k in names if f"demo_{k}" in data.files}
            self.demos.load(demo, gamma)
        self._obs = None  # episodes restart after a resume
        self.nstep.reset()
        self.close()
        # later episodes are drawn from each env's own generator: reseed them from the step
        for i, env in enumerate(self.timed):
            env.reset(
                seed=self.config.seed * ENV_SEED_STRIDE
                + i
                + STEP_SEED_FACTOR * self.state.env_steps
            )
