"""The policy's input vector, built by ONE function for training, evaluation and the driver.

A learned controller only works on inputs distributed like the ones it was trained on, so the
environment (`policy.rl.env`) and the deployed controllers (`policy.controllers.ddpg`,
`policy.controllers.ddpg_distilled`) call `build_observation` (through `InputMemory` when the
network has memory channels) with the configuration stored beside the weights.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from protocol.alpha5 import N_JOINTS

#: Range that random starts and goals are drawn from (rad, E D C B): the evaluation workspace.
WORKSPACE_LOW = np.array([0.4, 0.5, 0.5, 0.5])
WORKSPACE_HIGH = np.array([5.8, 2.9, 2.9, 2.8])
WORKSPACE_CENTRE = 0.5 * (WORKSPACE_LOW + WORKSPACE_HIGH)
WORKSPACE_HALF_RANGE = 0.5 * (WORKSPACE_HIGH - WORKSPACE_LOW)

#: Finite bounds the raw readings are clipped to (gymnasium needs finite observation bounds;
#: the arm's own angles stay within 0..2pi and its speed within ~1.2 rad/s).
Q_BOUNDS = (-0.5, 2.0 * np.pi + 0.5)
QDOT_BOUND = 5.0
#: the window's speeds (over `qdot_scale`) are clipped to this: a reading past twice the
#: no-load speed is noise or a glitch, not information about the arm
WINDOW_SPEED_BOUND = 2.0


@dataclass(frozen=True)
class ObservationConfig:
    """Which features the policy sees.

    The paper's state is `[q, qdot, q_req]` in raw units (`paper()`). Our default adds the
    error `q_req - q` twice: once over the joint's half-range (where to go) and once squashed
    at `fine_error_scale` (how close: a 0.005 rad error is a 0.1 input instead of 0.002), and
    normalises every feature to about [-1, 1] with fixed, known ranges, so no statistics need
    to travel with the weights.
    """

    normalise: bool = True
    include_error: bool = True
    fine_error_scale: float = 0.05  # rad; 0 disables the squashed fine-error channel
    qdot_scale: float = 1.2  # rad/s, the motors' no-load speed
    #: the policy's own previous action (4 entries, fractions of the current limit): lets
    #: it learn smooth commands and, with the readings, which arm it is on
    previous_action: bool = False
    #: s; > 0 adds a leaky mean of tanh(e / integral_error_scale) over this time constant
    #: (4 entries in [-1, 1]): a memory of the error that stays, so the network can learn
    #: to push through static friction or a heavier arm. 0 disables
    integral_tau: float = 0.0
    #: rad: where the integral channel's squashing bends (a steady 3 mrad reads 0.29)
    integral_error_scale: float = 0.01
    #: a window of the last `history` control periods: for each, the speed read then (over
    #: `qdot_scale`) and the action taken on it (8 entries per period, the newest first),
    #: so the network can see how this arm answers its commands (friction, a weak joint,
    #: latency) and adapt within an episode. 0 disables
    history: int = 0

    @classmethod
    def paper(cls) -> ObservationConfig:
        return cls(normalise=False, include_error=False, fine_error_scale=0.0)

    def __post_init__(self) -> None:
        # A file states these: a string or null here would only fail at the first step.
        for name in ("normalise", "include_error", "previous_action"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        for name in ("fine_error_scale", "qdot_scale", "integral_tau", "integral_error_scale"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r}")
        if self.qdot_scale <= 0 or self.fine_error_scale < 0:
            raise ValueError(
                f"qdot_scale must be > 0 and fine_error_scale >= 0, got {self.qdot_scale}, "
                f"{self.fine_error_scale}"
            )
        if isinstance(self.history, bool) or not isinstance(self.history, int):
            raise ValueError(f"history must be a whole number of periods, got {self.history!r}")
        if not 0 <= self.history <= 50:
            raise ValueError(f"history must be 0-50 periods, got {self.history}")
        if self.integral_tau < 0 or self.integral_error_scale <= 0:
            raise ValueError(
                "integral_tau must be >= 0 and integral_error_scale > 0, got "
                f"{self.integral_tau}, {self.integral_error_scale}"
            )
        if (self.previous_action or self.integral_tau > 0 or self.history) and not (
            self.include_error and self.fine_error_scale > 0
        ):
            raise ValueError("the memory channels follow the error channels: enable those too")

    @property
    def size(self) -> int:
        return (self.stateless_groups + self.memory_groups) * N_JOINTS

    @property
    def stateless_groups(self) -> int:
        """Groups of 4 built from one reading and the target alone."""
        n = 3
        if self.include_error:
            n += 1
            if self.fine_error_scale > 0:
                n += 1
        return n

    @property
    def memory_groups(self) -> int:
        """Groups of 4 that carry the past (`InputMemory`): previous action, error integral,
        and two per period of the window (speed, action)."""
        return int(self.previous_action) + int(self.integral_tau > 0) + 2 * self.history

    @property
    def has_memory(self) -> bool:
        return self.memory_groups > 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ObservationConfig:
        if not isinstance(data, dict):
            raise ValueError(f"the observation config must be an object, got {data!r:.80}")
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown observation config keys: {sorted(unknown)}")
        return cls(**data)


@lru_cache(maxsize=16)
def _affine(config: ObservationConfig) -> tuple[np.ndarray, np.ndarray]:
    """(offset, scale) applied to [q, qdot, q_req, e(, e)] before the fine channel's tanh."""
    zeros, ones = np.zeros(N_JOINTS), np.ones(N_JOINTS)
    if config.normalise:
        offsets = [WORKSPACE_CENTRE, zeros, WORKSPACE_CENTRE]
        scales = [1 / WORKSPACE_HALF_RANGE, ones / config.qdot_scale, 1 / WORKSPACE_HALF_RANGE]
        err_scale = 1 / WORKSPACE_HALF_RANGE
    else:
        offsets, scales, err_scale = [zeros, zeros, zeros], [ones, ones, ones], ones
    if config.include_error:
        offsets.append(zeros)
        scales.append(err_scale)
        if config.fine_error_scale > 0:
            offsets.append(zeros)
            scales.append(ones / config.fine_error_scale)
    offset, scale = np.concatenate(offsets), np.concatenate(scales)
    offset.flags.writeable = False  # shared by every call (cached)
    scale.flags.writeable = False
    return offset, scale


def checked_inputs(q: Any, qdot: Any, target: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A learned controller's reading and target as float arrays, or a ValueError saying what
    is wrong: a network fed NaN or a wrong shape answers with nonsense, not an error."""
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (N_JOINTS,) or not np.all(np.isfinite(target)):
        raise ValueError(f"target must be 4 finite angles (rad, E D C B), got {target!r}")
    q = np.asarray(q, dtype=np.float64)
    qdot = np.asarray(qdot, dtype=np.float64)
    if q.shape != (N_JOINTS,) or qdot.shape != (N_JOINTS,):
        raise ValueError(
            f"state.q and state.qdot must have shape (4,), got {q.shape}, {qdot.shape}"
        )
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qdot))):
        raise ValueError(f"state must be finite, got q={q}, qdot={qdot}")
    return q, qdot, target


def build_observation(
    q: np.ndarray,
    qdot: np.ndarray,
    q_req: np.ndarray,
    config: ObservationConfig,
    memory: InputMemory | None = None,
) -> np.ndarray:
    """Observation (float32) from joint angles, speeds and the requested angles, E D C B,
    followed by the memory channels (`memory`'s, required when the config has them).

    Runs every control period, so it is a handful of numpy calls on one small buffer.
    """
    q = np.asarray(q, dtype=np.float64)
    qdot = np.asarray(qdot, dtype=np.float64)
    q_req = np.asarray(q_req, dtype=np.float64)
    if q.shape != (N_JOINTS,) or qdot.shape != (N_JOINTS,) or q_req.shape != (N_JOINTS,):
        raise ValueError(
            f"q, qdot and q_req must each have shape (4,), got {q.shape}, {qdot.shape}, "
            f"{q_req.shape}"
        )
    offset, scale = _affine(config)
    x = np.empty(offset.size)
    x[0:4] = q
    x[4:8] = qdot
    x[8:12] = q_req
    np.clip(x[0:4], Q_BOUNDS[0], Q_BOUNDS[1], out=x[0:4])
    np.clip(x[4:8], -QDOT_BOUND, QDOT_BOUND, out=x[4:8])
    np.clip(x[8:12], Q_BOUNDS[0], Q_BOUNDS[1], out=x[8:12])
    if config.include_error:
        np.subtract(x[8:12], x[0:4], out=x[12:16])
        if offset.size > 16:
            x[16:20] = x[12:16]
    x -= offset
    x *= scale
    if offset.size > 16:
        np.tanh(x[16:20], out=x[16:20])
    if not config.has_memory:
        return x.astype(np.float32)
    if memory is None:
        raise ValueError("this observation has memory channels: pass its InputMemory")
    return np.concatenate([x, memory.channels()]).astype(np.float32)


class InputMemory:
    """What the policy's memory channels hold, updated once per control period by the env in
    training and by the controller at run time, through the same two calls:

        obs = memory.observe(q, qdot, q_req)   # folds this reading's error in, builds obs
        memory.acted(action)                   # the action computed from obs

    The integral is a leaky mean (time constant `integral_tau`, period `dt`) of the squashed
    error of the readings the policy saw; nothing is reset but by `reset()`, at the start of
    an episode or a run, so the network, not a rule, decides what a target change means.
    The window (`history`) shifts in the speed read and the action taken each period.
    """

    def __init__(self, config: ObservationConfig, dt: float) -> None:
        if not dt > 0:
            raise ValueError(f"control period must be > 0, got {dt}")
        self.config = config
        self.dt = float(dt)
        self.leak = float(np.exp(-dt / config.integral_tau)) if config.integral_tau > 0 else 0.0
        self.reset()

    def reset(self) -> None:
        self.prev_action = np.zeros(N_JOINTS)
        self.integral = np.zeros(N_JOINTS)
        #: the window, newest first: row k is (speed read, action taken) k + 1 periods ago
        self.window = np.zeros((self.config.history, 2 * N_JOINTS))
        self._speed = np.zeros(N_JOINTS)  # this period's speed reading, until `acted`

    def observe(self, q: np.ndarray, qdot: np.ndarray, q_req: np.ndarray) -> np.ndarray:
        if self.config.integral_tau > 0:
            error = np.tanh((np.asarray(q_req) - np.asarray(q)) / self.config.integral_error_scale)
            self.integral = self.leak * self.integral + (1.0 - self.leak) * error
        if self.config.history:
            speed = np.asarray(qdot, dtype=np.float64) / self.config.qdot_scale
            self._speed = np.clip(speed, -WINDOW_SPEED_BOUND, WINDOW_SPEED_BOUND)
        return build_observation(q, qdot, q_req, self.config, self)

    def acted(self, action: np.ndarray) -> None:
        self.prev_action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        if self.config.history:
            self.window[1:] = self.window[:-1]
            self.window[0, :N_JOINTS] = self._speed
            self.window[0, N_JOINTS:] = self.prev_action

    def channels(self) -> np.ndarray:
        parts = []
        if self.config.previous_action:
            parts.append(self.prev_action)
        if self.config.integral_tau > 0:
            parts.append(self.integral)
        if self.config.history:
            parts.append(self.window.ravel())
        return np.concatenate(parts) if parts else np.zeros(0)


def observation_bounds(config: ObservationConfig) -> tuple[np.ndarray, np.ndarray]:
    """Finite (low, high) that every `build_observation` output lies within."""
    q_lo = np.full(N_JOINTS, Q_BOUNDS[0])
    q_hi = np.full(N_JOINTS, Q_BOUNDS[1])
    v = np.full(N_JOINTS, QDOT_BOUND)
    e_hi = q_hi - q_lo
    if config.normalise:
        q_lo, q_hi = (
            (q_lo - WORKSPACE_CENTRE) / WORKSPACE_HALF_RANGE,
            (q_hi - WORKSPACE_CENTRE) / WORKSPACE_HALF_RANGE,
        )
        v = v / config.qdot_scale
        e_hi = e_hi / WORKSPACE_HALF_RANGE
    lows = [q_lo, -v, q_lo]
    highs = [q_hi, v, q_hi]
    if config.include_error:
        lows.append(-e_hi)
        highs.append(e_hi)
        if config.fine_error_scale > 0:
            lows.append(-np.ones(N_JOINTS))
            highs.append(np.ones(N_JOINTS))
    for _ in range(int(config.previous_action) + int(config.integral_tau > 0)):  # in [-1, 1]
        lows.append(-np.ones(N_JOINTS))
        highs.append(np.ones(N_JOINTS))
    for _ in range(config.history):  # a speed (clipped), then an action in [-1, 1]
        lows += [np.full(N_JOINTS, -WINDOW_SPEED_BOUND), -np.ones(N_JOINTS)]
        highs += [np.full(N_JOINTS, WINDOW_SPEED_BOUND), np.ones(N_JOINTS)]
    low = np.concatenate(lows).astype(np.float32)
    high = np.concatenate(highs).astype(np.float32)
    return low, high
