"""n-step returns (`DDPGConfig.n_step`): each stored transition carries up to n rewards.

With n steps the critic's target is `r_t + g r_t+1 + ... + g^(n-1) r_t+n-1 + g^n Q'(s_t+n, ...)`
(D4PG, FastTD3): what an arrival costs n periods later reaches the state that caused it in one
update instead of n. The transitions are built as the envs step, so the buffer, the sampler
and the update stay one-step shaped: a transition is (s_t, a_t, R, s_t+m, discount) with
`discount` = g^m, or 0 when the episode terminated within the m steps. At the end of an
episode (the 20 s truncation) the last n-1 transitions are stored with fewer rewards
(m < n) and bootstrap from the final state, as a truncated episode still does.

With n = 1 a round passes through unchanged, its discount g (0 where terminated).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Transitions:
    """Transitions ready for the buffer, one per row."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray
    #: the bootstrap's multiplier: gamma ** (rewards summed), 0 where the episode terminated
    discounts: np.ndarray
    #: the env each row came from
    envs: np.ndarray


class NStepReturns:
    """Per env, the last n-1 steps not yet stored; `push` a round, get what is complete."""

    def __init__(self, num_envs: int, n: int, gamma: float) -> None:
        if n < 1:
            raise ValueError(f"n_step must be >= 1, got {n}")
        self.n = n
        self.gamma = gamma
        #: per env: (obs, action, reward) of the steps whose n-step return is still open
        self.pending: list[deque[tuple[np.ndarray, np.ndarray, float]]] = [
            deque() for _ in range(num_envs)
        ]

    def push(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        next_obs: np.ndarray,
        terms: np.ndarray,
        dones: np.ndarray,
    ) -> Transitions:
        """One round (row i: env i's step); `dones` marks an episode that ended (terminated
        or truncated) at this step, `terms` the terminated ones (no bootstrap)."""
        if self.n == 1:
            discounts = (self.gamma * (1.0 - terms)).astype(np.float32)
            return Transitions(obs, actions, rewards, next_obs, discounts, np.arange(len(obs)))
        rows: list[tuple[np.ndarray, np.ndarray, float, np.ndarray, float, int]] = []
        for i, queue in enumerate(self.pending):
            queue.append((obs[i], actions[i], float(rewards[i])))
            if terms[i] or dones[i]:
                while queue:  # the episode ended: every open return closes here
                    rows.append(self._close(queue, next_obs[i], bool(terms[i]), i))
                    queue.popleft()
            elif len(queue) == self.n:
                rows.append(self._close(queue, next_obs[i], False, i))
                queue.popleft()
        if not rows:
            dim, act = obs.shape[1], actions.shape[1]
            empty = np.zeros((0, dim), obs.dtype)
            return Transitions(
                empty,
                np.zeros((0, act), actions.dtype),
                np.zeros(0),
                empty.copy(),
                np.zeros(0, np.float32),
                np.zeros(0, int),
            )
        o, a, r, o2, d, e = zip(*rows, strict=True)
        return Transitions(
            np.stack(o),
            np.stack(a),
            np.array(r),
            np.stack(o2),
            np.array(d, np.float32),
            np.array(e),
        )

    def _close(
        self,
        queue: deque[tuple[np.ndarray, np.ndarray, float]],
        last_obs: np.ndarray,
        terminated: bool,
        env: int,
    ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, float, int]:
        """The return from the queue's first step to `last_obs`, and its bootstrap discount."""
        ret = 0.0
        for k, (_, _, reward) in enumerate(queue):
            ret += self.gamma**k * reward
        discount = 0.0 if terminated else self.gamma ** len(queue)
        first_obs, first_action, _ = queue[0]
        return first_obs, first_action, ret, last_obs, discount, env

    def reset(self) -> None:
        """Drop every open return (the envs were reset without ending their episodes)."""
        for queue in self.pending:
            queue.clear()
