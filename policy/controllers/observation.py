"""The policy's input vector, built by ONE function for training, evaluation and the driver.

A learned controller only works on inputs distributed like the ones it was trained on, so the
environment (`policy.rl.env`) and the deployed controllers (`policy.controllers.ddpg`,
`policy.controllers.ddpg_distilled`) call `build_observation` (through `InputMemory` when the
network has memory channels) with the configuration stored beside the weights.

Each group of inputs holds one entry per joint of the arm, in its joint order; the angles are
normalised by the arm's `Workspace` (`Workspace.of(model)`; the Alpha 5's by default).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from functools import lru_cache
from types import MappingProxyType
from typing import Any

import numpy as np

from protocol.alpha5 import N_JOINTS
from protocol.models import ALPHA5, ArmModel, ArmModelName

#: Range that random starts and goals are drawn from (rad, E D C B): the Alpha 5's evaluation
#: workspace, chosen for the paper's evaluation (not derived from its limits).
WORKSPACE_LOW = np.array([0.4, 0.5, 0.5, 0.5])
WORKSPACE_HIGH = np.array([5.8, 2.9, 2.9, 2.8])
WORKSPACE_CENTRE = 0.5 * (WORKSPACE_LOW + WORKSPACE_HIGH)
WORKSPACE_HALF_RANGE = 0.5 * (WORKSPACE_HIGH - WORKSPACE_LOW)
#: rad: how far inside its factory envelope an arm without a chosen workspace draws starts and
#: goals (about the Alpha's own margin: its E and D sit 0.4-0.5 rad inside theirs)
WORKSPACE_INSET_RAD = 0.4

#: Finite bounds the raw readings are clipped to (gymnasium needs finite observation bounds;
#: the arm's own angles stay within 0..2pi and its speed within ~1.2 rad/s).
Q_BOUNDS = (-0.5, 2.0 * np.pi + 0.5)
QDOT_BOUND = 5.0
#: the window's speeds (over `qdot_scale`) are clipped to this: a reading past twice the
#: no-load speed is noise or a glitch, not information about the arm
WINDOW_SPEED_BOUND = 2.0


@dataclass(frozen=True)
class Workspace:
    """Per joint (the arm's joint order), the range starts and goals are drawn from: the
    evaluation workspace. Its centre and half-range normalise the angle inputs and scale the
    shaped reward's distance; its size is the arm's joint count."""

    low: tuple[float, ...]
    high: tuple[float, ...]

    def __post_init__(self) -> None:
        low = tuple(float(v) for v in self.low)
        high = tuple(float(v) for v in self.high)
        if not low or len(low) != len(high):
            raise ValueError(f"workspace needs one (low, high) per joint, got {low} .. {high}")
        if not all(math.isfinite(v) for v in (*low, *high)) or any(
            lo >= hi for lo, hi in zip(low, high, strict=True)
        ):
            raise ValueError(f"workspace must be finite ranges low < high, got {low} .. {high}")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    @classmethod
    def of(cls, model: ArmModel) -> Workspace:
        """`model`'s workspace: the Alpha 5's chosen one, or the factory envelope of any other
        arm inset by `WORKSPACE_INSET_RAD` per side."""
        if model.name in CHOSEN_WORKSPACES:
            return CHOSEN_WORKSPACES[model.name]
        ranges = [model.position_limits[d] for d in model.joints]
        return cls(
            tuple(lo + WORKSPACE_INSET_RAD for lo, _ in ranges),
            tuple(hi - WORKSPACE_INSET_RAD for _, hi in ranges),
        )

    @property
    def n_joints(self) -> int:
        return len(self.low)

    @property
    def centre(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.low) + np.asarray(self.high))

    @property
    def half_range(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.high) - np.asarray(self.low))


#: the Alpha 5's evaluation workspace (`WORKSPACE_LOW` .. `WORKSPACE_HIGH`)
ALPHA5_WORKSPACE = Workspace(tuple(WORKSPACE_LOW), tuple(WORKSPACE_HIGH))
#: workspaces chosen rather than derived from the factory envelope, by model name
CHOSEN_WORKSPACES: Mapping[str, Workspace] = MappingProxyType(
    {ArmModelName.ALPHA5.value: ALPHA5_WORKSPACE}
)


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
    #: the error read when the target last changed (over the joint's half-range, as the
    #: error channel): which side of the goal the arm came from and how far, so the network
    #: can tell a crossing (an overshoot, measured against that step) from an approach; the
    #: error alone reads the same either way
    target_step: bool = False

    @classmethod
    def paper(cls) -> ObservationConfig:
        return cls(normalise=False, include_error=False, fine_error_scale=0.0)

    def __post_init__(self) -> None:
        # A file states these: a string or null here would only fail at the first step.
        for name in ("normalise", "include_error", "previous_action", "target_step"):
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
        if self.has_memory and not (self.include_error and self.fine_error_scale > 0):
            raise ValueError("the memory channels follow the error channels: enable those too")

    @property
    def size(self) -> int:
        """Inputs for the Alpha 5's four joints; `size_for` any arm's."""
        return self.size_for(N_JOINTS)

    def size_for(self, n_joints: int) -> int:
        """Inputs for an arm of `n_joints` joints: one per joint in each group."""
        return (self.stateless_groups + self.memory_groups) * n_joints

    @property
    def stateless_groups(self) -> int:
        """Groups (one entry per joint) built from one reading and the target alone."""
        n = 3
        if self.include_error:
            n += 1
            if self.fine_error_scale > 0:
                n += 1
        return n

    @property
    def memory_groups(self) -> int:
        """Groups (one entry per joint) that carry the past (`InputMemory`): previous action,
        error integral, two per period of the window (speed, action), the target's step."""
        return (
            int(self.previous_action)
            + int(self.integral_tau > 0)
            + 2 * self.history
            + int(self.target_step)
        )

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
def _affine(config: ObservationConfig, workspace: Workspace) -> tuple[np.ndarray, np.ndarray]:
    """(offset, scale) applied to [q, qdot, q_req, e(, e)] before the fine channel's tanh."""
    n = workspace.n_joints
    zeros, ones = np.zeros(n), np.ones(n)
    centre, half_range = workspace.centre, workspace.half_range
    if config.normalise:
        offsets = [centre, zeros, centre]
        scales = [1 / half_range, ones / config.qdot_scale, 1 / half_range]
        err_scale = 1 / half_range
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


def checked_inputs(
    q: Any, qdot: Any, target: Any, model: ArmModel = ALPHA5
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A learned controller's reading and target (for an arm of `model`) as float arrays, or
    a ValueError saying what is wrong: a network fed NaN or a wrong shape answers with
    nonsense, not an error."""
    n, order = model.n_joints, " ".join(model.joint_letters)
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (n,) or not np.all(np.isfinite(target)):
        raise ValueError(f"target must be {n} finite angles (rad, {order}), got {target!r}")
    q = np.asarray(q, dtype=np.float64)
    qdot = np.asarray(qdot, dtype=np.float64)
    if q.shape != (n,) or qdot.shape != (n,):
        raise ValueError(
            f"state.q and state.qdot must have shape ({n},), got {q.shape}, {qdot.shape}"
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
    workspace: Workspace = ALPHA5_WORKSPACE,
) -> np.ndarray:
    """Observation (float32) from joint angles, speeds and the requested angles (the arm's
    joint order, one entry per joint of `workspace`), followed by the memory channels
    (`memory`'s, required when the config has them).

    Runs every control period, so it is a handful of numpy calls on one small buffer.
    """
    q = np.asarray(q, dtype=np.float64)
    qdot = np.asarray(qdot, dtype=np.float64)
    q_req = np.asarray(q_req, dtype=np.float64)
    n = workspace.n_joints
    if q.shape != (n,) or qdot.shape != (n,) or q_req.shape != (n,):
        raise ValueError(
            f"q, qdot and q_req must each have shape ({n},), got {q.shape}, {qdot.shape}, "
            f"{q_req.shape}"
        )
    offset, scale = _affine(config, workspace)
    x = np.empty(offset.size)
    q_, v_, r_, e_, f_ = (slice(k * n, (k + 1) * n) for k in range(5))
    x[q_] = q
    x[v_] = qdot
    x[r_] = q_req
    np.clip(x[q_], Q_BOUNDS[0], Q_BOUNDS[1], out=x[q_])
    np.clip(x[v_], -QDOT_BOUND, QDOT_BOUND, out=x[v_])
    np.clip(x[r_], Q_BOUNDS[0], Q_BOUNDS[1], out=x[r_])
    if config.include_error:
        np.subtract(x[r_], x[q_], out=x[e_])
        if offset.size > 4 * n:
            x[f_] = x[e_]
    x -= offset
    x *= scale
    if offset.size > 4 * n:
        np.tanh(x[f_], out=x[f_])
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
    The target's step (`target_step`) is the error of the first reading observed with the
    current target: a target is new when it differs from the last one observed.
    """

    def __init__(
        self, config: ObservationConfig, dt: float, workspace: Workspace = ALPHA5_WORKSPACE
    ) -> None:
        if not dt > 0:
            raise ValueError(f"control period must be > 0, got {dt}")
        self.config = config
        self.dt = float(dt)
        self.workspace = workspace
        self.leak = float(np.exp(-dt / config.integral_tau)) if config.integral_tau > 0 else 0.0
        self.reset()

    def reset(self) -> None:
        n = self.workspace.n_joints
        self.prev_action = np.zeros(n)
        self.integral = np.zeros(n)
        #: the window, newest first: row k is (speed read, action taken) k + 1 periods ago
        self.window = np.zeros((self.config.history, 2 * n))
        self._speed = np.zeros(n)  # this period's speed reading, until `acted`
        self.step = np.zeros(n)  # the target's step, over the half-range
        self._target: np.ndarray | None = None  # the target it was read for

    def observe(self, q: np.ndarray, qdot: np.ndarray, q_req: np.ndarray) -> np.ndarray:
        if self.config.integral_tau > 0:
            error = np.tanh((np.asarray(q_req) - np.asarray(q)) / self.config.integral_error_scale)
            self.integral = self.leak * self.integral + (1.0 - self.leak) * error
        if self.config.history:
            speed = np.asarray(qdot, dtype=np.float64) / self.config.qdot_scale
            self._speed = np.clip(speed, -WINDOW_SPEED_BOUND, WINDOW_SPEED_BOUND)
        if self.config.target_step:
            target = np.array(q_req, dtype=np.float64)
            if self._target is None or not np.array_equal(target, self._target):
                self._target = target
                bounded = np.clip(target, *Q_BOUNDS) - np.clip(np.asarray(q), *Q_BOUNDS)
                self.step = bounded / self.workspace.half_range
        return build_observation(q, qdot, q_req, self.config, self, self.workspace)

    def acted(self, action: np.ndarray) -> None:
        self.prev_action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        if self.config.history:
            n = self.workspace.n_joints
            self.window[1:] = self.window[:-1]
            self.window[0, :n] = self._speed
            self.window[0, n:] = self.prev_action

    def channels(self) -> np.ndarray:
        parts = []
        if self.config.previous_action:
            parts.append(self.prev_action)
        if self.config.integral_tau > 0:
            parts.append(self.integral)
        if self.config.history:
            parts.append(self.window.ravel())
        if self.config.target_step:
            parts.append(self.step)
        return np.concatenate(parts) if parts else np.zeros(0)


def observation_bounds(
    config: ObservationConfig, workspace: Workspace = ALPHA5_WORKSPACE
) -> tuple[np.ndarray, np.ndarray]:
    """Finite (low, high) that every `build_observation` output (for `workspace`'s arm) lies
    within."""
    n = workspace.n_joints
    centre, half_range = workspace.centre, workspace.half_range
    q_lo = np.full(n, Q_BOUNDS[0])
    q_hi = np.full(n, Q_BOUNDS[1])
    v = np.full(n, QDOT_BOUND)
    e_hi = q_hi - q_lo
    if config.normalise:
        q_lo, q_hi = (
            (q_lo - centre) / half_range,
            (q_hi - centre) / half_range,
        )
        v = v / config.qdot_scale
        e_hi = e_hi / half_range
    lows = [q_lo, -v, q_lo]
    highs = [q_hi, v, q_hi]
    if config.include_error:
        lows.append(-e_hi)
        highs.append(e_hi)
        if config.fine_error_scale > 0:
            lows.append(-np.ones(n))
            highs.append(np.ones(n))
    for _ in range(int(config.previous_action) + int(config.integral_tau > 0)):  # in [-1, 1]
        lows.append(-np.ones(n))
        highs.append(np.ones(n))
    for _ in range(config.history):  # a speed (clipped), then an action in [-1, 1]
        lows += [np.full(n, -WINDOW_SPEED_BOUND), -np.ones(n)]
        highs += [np.full(n, WINDOW_SPEED_BOUND), np.ones(n)]
    if config.target_step:  # an error, over the half-range whatever `normalise` says
        step = (np.full(n, Q_BOUNDS[1]) - np.full(n, Q_BOUNDS[0])) / half_range
        lows.append(-step)
        highs.append(step)
    low = np.concatenate(lows).astype(np.float32)
    high = np.concatenate(highs).astype(np.float32)
    return low, high
