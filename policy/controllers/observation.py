"""The policy's input vector, built by ONE function for training, evaluation and the driver.

A learned controller only works on inputs distributed like the ones it was trained on, so the
environment (`policy.rl.env`) and the deployed controller (`policy.controllers.ddpg_distilled`)
both call `build_observation` with the configuration stored beside the weights.
"""

from __future__ import annotations

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

    @classmethod
    def paper(cls) -> ObservationConfig:
        return cls(normalise=False, include_error=False, fine_error_scale=0.0)

    @property
    def size(self) -> int:
        n = 3
        if self.include_error:
            n += 1
            if self.fine_error_scale > 0:
                n += 1
        return n * N_JOINTS

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ObservationConfig:
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


def build_observation(
    q: np.ndarray, qdot: np.ndarray, q_req: np.ndarray, config: ObservationConfig
) -> np.ndarray:
    """Observation (float32) from joint angles, speeds and the requested angles, E D C B.

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
    return x.astype(np.float32)


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
    low = np.concatenate(lows).astype(np.float32)
    high = np.concatenate(highs).astype(np.float32)
    return low, high
