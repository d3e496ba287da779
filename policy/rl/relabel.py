"""Goal relabelling (hindsight experience replay, Andrychowicz et al. 2017) for `ReachAlphaEnv`.

Valid here because the reward is a function of the true angles, speeds, the actions and the
goal alone (`reward_terms`), and the goal is part of the observation: an episode that was
after goal g is also a correct episode after any other goal g', once its observations and
rewards are computed for g'. Each finished episode is stored again `her_goals` times, each
time with a goal drawn from the true angles the arm itself passed through in that episode,
so the buffer holds arrivals (and overshoots, and holds at rest) at goals the arm reached:
the transitions near a goal that a random policy seldom makes.

The observation is rebuilt from the start of the episode with the new goal: the error
channels are the goal minus the same noisy readings, and the error integral
(`InputMemory`) is folded again along the episode, since it depends on the goal's whole
history. The readings, the actions and the true states are the episode's own; nothing is
simulated again.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from policy.controllers.observation import InputMemory, observation_bounds
from policy.rl.env import ReachAlphaEnv, overshoot_ratio, reward_terms


@dataclass
class EpisodeTrace:
    """What one env's episode needs to be replayed for another goal: per observation the
    noisy reading it was built from, per step the action, the true state after it and
    whether the arm stayed in bounds."""

    start: np.ndarray  #: true angles at reset (the overshoot term's step is from there)
    readings_q: list[np.ndarray] = field(default_factory=list)
    readings_qdot: list[np.ndarray] = field(default_factory=list)
    true_q: list[np.ndarray] = field(default_factory=list)  #: at reset, then after each step
    true_qdot: list[np.ndarray] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    in_bounds: list[bool] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.actions)


@dataclass(frozen=True)
class Relabelled:
    """Transitions of replayed episodes, first axis = transition, as the buffer takes them."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray
    terms: np.ndarray

    @classmethod
    def empty(cls, obs_dim: int, act_dim: int) -> Relabelled:
        return cls(
            np.zeros((0, obs_dim), np.float32),
            np.zeros((0, act_dim), np.float32),
            np.zeros(0),
            np.zeros((0, obs_dim), np.float32),
            np.zeros(0),
        )

    @classmethod
    def concatenate(cls, parts: list[Relabelled]) -> Relabelled:
        return cls(
            np.concatenate([p.obs for p in parts]),
            np.concatenate([p.actions for p in parts]),
            np.concatenate([p.rewards for p in parts]),
            np.concatenate([p.next_obs for p in parts]),
            np.concatenate([p.terms for p in parts]),
        )

    def __len__(self) -> int:
        return len(self.obs)


class GoalRelabeller:
    """Traces each env's episode (`started`, `stepped`) and, when it ends (`finished`),
    replays it for `goals` goals drawn from the true angles of its own steps."""

    def __init__(self, envs: list[ReachAlphaEnv], goals: int, rng: np.random.Generator) -> None:
        if goals < 0:
            raise ValueError(f"her_goals must be >= 0, got {goals}")
        self.envs = envs
        self.goals = goals
        self.rng = rng
        self.traces: list[EpisodeTrace | None] = [None] * len(envs)

    def started(self, i: int) -> None:
        """Env i was just reset: its first observation's reading and the true start."""
        env = self.envs[i]
        trace = EpisodeTrace(start=np.array(env.start, dtype=np.float64))
        self._read(trace, env)
        trace.true_q.append(np.array(env.arm.q, dtype=np.float64))
        trace.true_qdot.append(np.array(env.arm.qdot, dtype=np.float64))
        self.traces[i] = trace

    def stepped(self, i: int, action: np.ndarray, info: dict[str, object]) -> None:
        """Env i took `action`; `info` is its step's (true state after it, in bounds). The
        reading recorded is the one its next observation was built from."""
        trace = self.traces[i]
        if trace is None:
            raise RuntimeError(f"env {i} stepped before `started`")
        env = self.envs[i]
        trace.actions.append(np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0))
        trace.true_q.append(np.array(info["q"], dtype=np.float64))
        trace.true_qdot.append(np.array(info["qdot"], dtype=np.float64))
        trace.in_bounds.append(bool(info["in_bounds"]))
        self._read(trace, env)

    def finished(self, i: int) -> Relabelled | None:
        """Env i's episode ended (before its reset): its replays, or None if none asked."""
        trace, self.traces[i] = self.traces[i], None
        if trace is None or not len(trace) or self.goals == 0:
            return None
        picks = self.rng.integers(1, len(trace) + 1, size=self.goals)
        return Relabelled.concatenate([self.replay(i, trace, trace.true_q[k]) for k in picks])

    def replay(self, i: int, trace: EpisodeTrace, goal: np.ndarray) -> Relabelled:
        """The episode's transitions as they would have been after `goal`."""
        env = self.envs[i]
        config = env.config
        memory = InputMemory(config.observation, env.control_dt, env.arm_workspace)
        n = len(trace)
        low, high = observation_bounds(config.observation, env.arm_workspace)  # the env clips
        obs = np.empty((n + 1, low.size), np.float32)
        rewards = np.empty(n)
        prev_action = np.zeros_like(goal)
        peak = np.zeros_like(goal)
        for t in range(n + 1):
            obs[t] = np.clip(
                memory.observe(trace.readings_q[t], trace.readings_qdot[t], goal), low, high
            )
            if t == n:
                break
            action = trace.actions[t]
            memory.acted(action)
            terms = reward_terms(
                trace.true_q[t + 1],
                trace.true_qdot[t + 1],
                goal,
                action,
                prev_action,
                trace.in_bounds[t],
                config.reward,
                trace.true_q[t],
                trace.start,
                env.scales,
                peak,
            )
            floor = config.reward.overshoot_floor
            peak = np.maximum(peak, overshoot_ratio(trace.true_q[t + 1], goal, trace.start, floor))
            rewards[t] = sum(terms.values())
            prev_action = action
        return Relabelled(
            obs[:-1].copy(),
            np.asarray(trace.actions, np.float32),
            rewards,
            obs[1:].copy(),
            np.zeros(n),  # the env never terminates (docs of ReachAlphaEnv)
        )

    @staticmethod
    def _read(trace: EpisodeTrace, env: ReachAlphaEnv) -> None:
        q, qdot = env.last_reading
        trace.readings_q.append(np.array(q, dtype=np.float64))
        trace.readings_qdot.append(np.array(qdot, dtype=np.float64))
