"""Env stepping in a second process, one round ahead of the learner (`collector_process`).

On a machine with two cores the learner's gradient updates and the envs' physics are each
about half of a training round; run in one process they add up. With `collector_process` the
envs live in a child process (`CollectorProcess`): while the learner updates on the replay
buffer, the child steps round k+1 with the actor the learner had after round k-1 (its weights
travel with each request, about 0.3 MB). The lag is fixed at one round, so a run is still
deterministic for its seed, though not identical to an in-process run of the same config.

`EnvWorker` is the stepping itself (envs behind TimeLimit, OU exploration or SAC's samples,
uniform actions before learning starts, a numpy copy of the actor); the child process only
serves it.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from policy.controllers.weights import LAYERS, LEAKY_RELU_SLOPE, ActorWeights
from policy.rl.config import ENV_SEED_STRIDE, STEP_SEED_FACTOR, Algorithm, DDPGConfig
from policy.rl.env import ReachAlphaEnv, time_limited
from policy.rl.exploration import GaussianSampler, OUNoise
from policy.rl.relabel import GoalRelabeller, Relabelled

#: the thread-count variables of the BLAS libraries numpy may use, set to 1 for the child
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
#: seconds a request may take before the child is declared stuck (a round is milliseconds)
ROUND_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class Round:
    """One round of `num_envs` transitions, and the episodes it finished."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray
    terms: np.ndarray
    dones: np.ndarray  #: the episode ended at this step (terminated or truncated)
    returns: tuple[float, ...]  #: undiscounted return of each episode that ended
    #: the ended episodes replayed for other goals (`her_goals`); None when off
    relabelled: Relabelled | None = None


class EnvWorker:
    """The envs a run collects from, with their exploration, stepped a round at a time."""

    def __init__(self, config: DDPGConfig, from_step: int) -> None:
        self.config = config
        self.envs = [ReachAlphaEnv(config.env) for _ in range(config.num_envs)]
        self.timed = [time_limited(env) for env in self.envs]
        self.model = config.env.model
        #: the child's own stream (exploration, warm-up actions), seeded from the run's seed
        #: and the step it starts at, so a resumed run does not replay the same noise
        self.rng = np.random.default_rng([config.seed, 1, from_step])
        self.noise = OUNoise(
            (config.num_envs, self.model.n_joints), config.ou_theta, config.ou_sigma, self.rng
        )
        seed = config.seed * ENV_SEED_STRIDE + STEP_SEED_FACTOR * from_step
        self.obs = np.stack([t.reset(seed=seed + i)[0] for i, t in enumerate(self.timed)])
        self.returns = np.zeros(config.num_envs)
        self.relabeller = GoalRelabeller(
            self.envs, config.her_goals, np.random.default_rng([config.seed, 2, from_step])
        )
        for i in range(config.num_envs):
            self.relabeller.started(i)
        self.actor: ActorWeights | None = None
        #: SAC's sampler over the same layers and the log-std head (`Algorithm.SAC`)
        self.sampler: GaussianSampler | None = None

    def set_actor(self, arrays: list[np.ndarray]) -> None:
        """The learner's actor as (W0, b0, W1, b1, W2, b2), torch's layout; SAC's log-std
        head (W, b) after them."""
        observation = self.config.env.observation
        if self.config.algorithm is Algorithm.SAC:
            self.sampler = GaussianSampler(arrays, LEAKY_RELU_SLOPE, self.rng)
            arrays = arrays[:6]
        self.actor = ActorWeights(
            tuple(arrays[0::2]),
            tuple(arrays[1::2]),
            LEAKY_RELU_SLOPE,
            observation,
            np.asarray(self.model.current_limits_mA, dtype=np.float64),
            {"layers": LAYERS},
            self.model,
        )

    def round(self, epsilon: float, uniform: bool) -> Round:
        """Step every env once: uniform random actions (`uniform`, before learning starts),
        SAC's samples, or the actor's plus `epsilon` times OU noise, clipped to [-1, 1]."""
        n = self.config.num_envs
        if uniform:
            actions = self.rng.uniform(-1, 1, size=(n, self.model.n_joints))
        elif self.sampler is not None:
            actions = self.sampler.sample(self.obs)
        else:
            if self.actor is None:
                raise RuntimeError("the collector has no actor yet")
            actions = self.actor.forward(self.obs) + epsilon * self.noise.sample()
        actions = np.clip(actions, -1.0, 1.0).astype(np.float32)
        next_obs = np.empty_like(self.obs)
        rewards = np.empty(n)
        terms = np.zeros(n)
        done = np.zeros(n, dtype=bool)
        for i, env in enumerate(self.timed):
            o, r, term, trunc, info = env.step(actions[i])
            next_obs[i], rewards[i], terms[i], done[i] = o, r, float(term), term or trunc
            self.relabeller.stepped(i, actions[i], info)
        self.returns += rewards
        obs, finished = self.obs, []
        self.obs = next_obs.copy()
        replays = []
        for j in np.nonzero(done)[0]:
            finished.append(float(self.returns[j]))
            self.returns[j] = 0.0
            replay = self.relabeller.finished(int(j))
            if replay is not None:
                replays.append(replay)
            self.obs[j] = self.timed[j].reset()[0]
            self.relabeller.started(int(j))
            self.noise.reset(int(j))
        relabelled = Relabelled.concatenate(replays) if replays else None
        return Round(obs, actions, rewards, next_obs, terms, done, tuple(finished), relabelled)


def _serve(conn: Connection, config: dict[str, Any], from_step: int) -> None:
    """The child's loop: answer each (actor arrays or None, epsilon, uniform) with a Round;
    None ends it. An exception is sent back, to be raised in the learner."""
    try:
        worker = EnvWorker(DDPGConfig.from_dict(config), from_step)
        while True:
            request = conn.recv()
            if request is None:
                return
            arrays, epsilon, uniform = request
            if arrays is not None:
                worker.set_actor(arrays)
            conn.send(worker.round(epsilon, uniform))
    except Exception as exc:  # the learner raises it, with the child's message
        conn.send(RuntimeError(f"collector process failed: {type(exc).__name__}: {exc}"))


class CollectorProcess:
    """An `EnvWorker` in a child process: `request()` starts a round, `result()` waits for it."""

    def __init__(self, config: DDPGConfig, from_step: int) -> None:
        ctx = mp.get_context("spawn")  # no forked torch or MuJoCo state in the child
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(
            target=_serve, args=(child, config.to_dict(), from_step), daemon=True
        )
        # one BLAS thread in the child: its small matrix products gain nothing from more,
        # and a second thread would take the learner's core
        saved = {name: os.environ.get(name) for name in BLAS_THREADS}
        os.environ.update(dict.fromkeys(BLAS_THREADS, "1"))
        try:
            self.process.start()
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value
        child.close()
        self._pending = False

    def request(self, actor: list[np.ndarray] | None, epsilon: float, uniform: bool) -> None:
        if self._pending:
            raise RuntimeError("a round is already in flight")
        self.conn.send((actor, epsilon, uniform))
        self._pending = True

    def result(self) -> Round:
        if not self._pending:
            raise RuntimeError("no round in flight")
        if not self.conn.poll(ROUND_TIMEOUT_S):
            raise RuntimeError(f"collector process gave no round in {ROUND_TIMEOUT_S:.0f} s")
        out = self.conn.recv()
        self._pending = False
        if isinstance(out, BaseException):
            raise out
        if not isinstance(out, Round):
            raise RuntimeError(f"collector process sent {type(out).__name__}, not a Round")
        return out

    def close(self) -> None:
        """End the child (after the round in flight, which is dropped)."""
        try:
            if self._pending and self.conn.poll(ROUND_TIMEOUT_S):
                self.conn.recv()
            self.conn.send(None)
        except (OSError, EOFError):
            pass
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()

    def __enter__(self) -> CollectorProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
