"""Inverse kinematics for end-effector moves, on the driver's own chain (`kinematics`).

The driver never sends KM_END_POS: it solves for joint angles here and sends them as joint
POSITION commands through the same gate as any other (limits, faults, the watchdog), so an
end-effector move is checked exactly like a joint move. The virtual arm solves KM_END_POS
with the same method (reach_sim_bridge/model/ik.py); tests/test_driver_xyz.py checks they agree.

What a 4-joint Alpha 5 can follow: the tool centre point's position uses E, D and C (base
yaw, shoulder, elbow); B (wrist roll) turns the tool about its own axis and does not move the
tool centre point, which lies on that axis. So B is free: it keeps the angle it starts with.

Method (`solve_position`): damped least squares on the position with E, D and C,
dq = J^T (J J^T + lambda^2 I)^-1 e, every iterate clamped to the position limits (the
factory ones of `protocol.alpha5` unless given tighter) and every step to `MAX_STEP_RAD`.
It starts from the present angles, then from seeds facing the target (E towards it and away
from it; D and C mid-range first, then on a 3 x 3 grid of their ranges), and takes the first
solution within `TOLERANCE_MM`. If none gets there the target is out of reach inside the
limits: `UnreachableError` says how close the best attempt came.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINTS
from reach_driver.errors import LimitError
from reach_driver.kinematics import tool_jacobian, tool_position

DAMPING = 0.01  # lambda (m)
MAX_STEP_RAD = 0.2
MAX_ITERATIONS = 150
TOLERANCE_MM = 1.0  # a target is reachable when a solution's tool centre point is this close
_CONVERGED_MM = 0.05
_ARM = 3  # E, D, C move the tool centre point; B (index 3) does not


class UnreachableError(LimitError):
    """No joint angles inside the position limits put the tool centre point at the target;
    nothing was sent. `distance_mm` is how close the best attempt came."""

    def __init__(self, message: str, distance_mm: float, best: np.ndarray) -> None:
        super().__init__(message)
        self.distance_mm = distance_mm
        self.best = best


@dataclass(frozen=True)
class Solution:
    q: np.ndarray  # E D C B (rad)
    error_mm: float  # distance of its tool centre point from the target
    iterations: int

    @property
    def reachable(self) -> bool:
        return self.error_mm <= TOLERANCE_MM


def factory_limits() -> np.ndarray:
    """4 x 2 [min, max] position limits of E D C B, as shipped (`protocol.alpha5`)."""
    return np.array([FACTORY_POSITION_LIMITS[d] for d in JOINTS], dtype=float)


def refine(target_m: np.ndarray, q0: np.ndarray, limits: np.ndarray) -> Solution:
    """Damped least squares on the position from q0 alone (E D C move; B kept)."""
    q = np.clip(np.asarray(q0, dtype=float), limits[:, 0], limits[:, 1])
    err_mm = checkpoint = math.inf
    it = 0
    for it in range(1, MAX_ITERATIONS + 1):
        tcp, jac = tool_jacobian(q)
        e = target_m - tcp
        err_mm = float(np.linalg.norm(e)) * 1000.0
        if err_mm < _CONVERGED_MM:
            break
        if it % 10 == 0:  # stalled against a limit, or out of reach: give up this start
            if err_mm > 0.99 * checkpoint:
                break
            checkpoint = err_mm
        j = jac[:, :_ARM]
        step = j.T @ np.linalg.solve(j @ j.T + DAMPING * DAMPING * np.eye(3), e)
        biggest = float(np.max(np.abs(step)))
        if biggest > MAX_STEP_RAD:
            step *= MAX_STEP_RAD / biggest
        q[:_ARM] = np.clip(q[:_ARM] + step, limits[:_ARM, 0], limits[:_ARM, 1])
    err_mm = float(np.linalg.norm(target_m - tool_position(q))) * 1000.0
    return Solution(q, err_mm, it)


def seeds(target_m: np.ndarray, q0: np.ndarray, limits: np.ndarray) -> list[np.ndarray]:
    """Where the solver starts: the present angles, then facing the target and away from it
    with D and C mid-range, then on a 3 x 3 grid of their ranges."""
    facing = math.atan2(float(target_m[1]), float(target_m[0])) % (2.0 * math.pi)
    span = limits[:, 1] - limits[:, 0]
    grid = [(1, 1)] + [(i, j) for i in range(3) for j in range(3) if (i, j) != (1, 1)]
    out = [np.asarray(q0, dtype=float).copy()]
    for yaw in (facing, (facing + math.pi) % (2.0 * math.pi)):
        for i, j in grid:
            d = limits[1, 0] + span[1] * (1 + 3 * i) / 8.0
            c = limits[2, 0] + span[2] * (1 + 3 * j) / 8.0
            out.append(np.array([yaw, d, c, q0[_ARM]]))
    return out


def solve_position(
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray | None = None,
) -> Solution:
    """Joint angles E D C B putting the tool centre point at `xyz_mm` (base frame, mm) inside
    `limits` (4 x 2 [min, max]; default the factory limits), B kept at q0's; the best attempt
    (check `reachable`)."""
    target = np.asarray(xyz_mm, dtype=float).reshape(-1)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise ValueError(f"target must be 3 finite numbers x y z in mm, got {xyz_mm!r}")
    start = np.asarray(q0, dtype=float).reshape(-1)
    if start.shape != (len(JOINTS),) or not np.all(np.isfinite(start)):
        raise ValueError(f"start angles must be 4 finite numbers E D C B, got {q0!r}")
    lim = factory_limits() if limits is None else np.asarray(limits, dtype=float)
    target_m = target / 1000.0
    best: Solution | None = None
    for seed in seeds(target_m, start, lim):
        sol = refine(target_m, seed, lim)
        if sol.reachable:
            return sol
        if best is None or sol.error_mm < best.error_mm:
            best = sol
    assert best is not None
    return best


def solve_or_refuse(
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray | None = None,
) -> np.ndarray:
    """`solve_position`'s angles, or `UnreachableError` naming the target and how far the
    closest reachable point is."""
    sol = solve_position(xyz_mm, q0, limits)
    if sol.reachable:
        return sol.q
    x, y, z = (float(v) for v in xyz_mm)
    raise UnreachableError(
        f"refused: tool target ({x:.1f}, {y:.1f}, {z:.1f}) mm is out of reach inside the "
        f"position limits: the closest the arm gets is {sol.error_mm:.1f} mm away (E D C "
        f"{' '.join(f'{v:.3f}' for v in sol.q[:_ARM])} rad); nothing was sent",
        sol.error_mm,
        sol.q,
    )
