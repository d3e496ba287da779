"""Inverse kinematics of the Alpha 5 for the base device's KM_END_POS and KM_END_VEL.

What a 4-joint arm can follow: the tool centre point's position (x, y, z) uses E, D and C
(yaw, shoulder pitch, elbow pitch), which then also fix the direction of the tool axis; B
(wrist roll) turns the tool about that axis and does not move the tool centre point, which
lies on it. So of a commanded pose the emulator follows the **position** and the **roll about
the tool axis** (the component of the commanded orientation about the tool axis the position
gives); the direction of the tool axis cannot be chosen and is ignored. Of a commanded
Cartesian velocity it follows the linear velocity and the angular velocity's component along
the tool axis.

Method (`solve`): damped least squares on the position with E, D and C,
dq = J^T (J J^T + lambda^2 I)^-1 e, each iterate clamped to the joint position limits and
each step to MAX_STEP_RAD; then B alone turns the remaining roll error out (B does not move
the tool centre point), wrapped into B's range. It tries the present angles first, then
seeds facing the target (E towards it and away from it; D and C mid-range first, then on a
3 x 3 grid of their ranges), and takes the first that reaches the position within
`TOLERANCE_MM`; if none does, the pose is unreachable. Velocities (`joint_rates`) use damped
least squares on the 4-row task [linear velocity; ROLL_WEIGHT x angular velocity about the
tool axis].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

DAMPING = 0.01  # lambda, in the task's units (m)
ROLL_WEIGHT = 0.05  # m per rad: a millimetre of position weighs as much as 0.02 rad of roll
MAX_STEP_RAD = 0.2
MAX_ITERATIONS = 150
TOLERANCE_MM = 1.0  # a pose is reachable when the solution's position is this close
_CONVERGED_MM = 0.05
_CONVERGED_RAD = 1e-3
_WRIST = 3


class Kinematics(Protocol):
    """What the solver needs of the arm (`Alpha5Arm.tcp_kinematics`)."""

    def tcp_kinematics(
        self, q: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]: ...


@dataclass(frozen=True)
class Solution:
    q: FloatArray  # E D C B (rad)
    position_error_mm: float
    roll_error_rad: float
    reachable: bool
    iterations: int


def rotation_rpy(roll: float, pitch: float, yaw: float) -> FloatArray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), the convention of KM_END_POS's three angles."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def roll_error(rot: FloatArray, target: FloatArray) -> float:
    """Angle (rad) to turn about the present tool axis (rot's z column) to bring the tool's x
    axis onto the target's x axis projected onto the plane normal to the tool axis."""
    axis = rot[:, 2]
    x_now = rot[:, 0]
    x_goal = target[:, 0] - axis * float(axis @ target[:, 0])
    if float(np.linalg.norm(x_goal)) < 1e-6:  # target x along the tool axis: use its y
        x_goal = np.cross(axis, target[:, 1] - axis * float(axis @ target[:, 1]))
    return math.atan2(float(axis @ np.cross(x_now, x_goal)), float(x_now @ x_goal))


def task_jacobian(rot: FloatArray, jacp: FloatArray, jacr: FloatArray) -> FloatArray:
    """4 x 4: position rows (m/rad), then the weighted roll about the tool axis."""
    return np.vstack([jacp, ROLL_WEIGHT * (rot[:, 2] @ jacr)])


def dls(jac: FloatArray, error: FloatArray, damping: float = DAMPING) -> FloatArray:
    """Damped least squares: J^T (J J^T + lambda^2 I)^-1 e."""
    jjt = jac @ jac.T + (damping * damping) * np.eye(jac.shape[0])
    return jac.T @ np.linalg.solve(jjt, error)


def _clamp(q: FloatArray, limits: FloatArray, continuous_wrist: bool) -> FloatArray:
    q = q.copy()
    if continuous_wrist:
        q[_WRIST] %= 2.0 * math.pi
    return np.clip(q, limits[:, 0], limits[:, 1])


def refine(
    arm: Kinematics,
    position_m: FloatArray,
    rot_target: FloatArray,
    q0: FloatArray,
    limits: FloatArray,
    continuous_wrist: bool = False,
) -> Solution:
    """Damped least squares from q0 alone: position with E D C, then the roll with B."""
    q = _clamp(np.asarray(q0, dtype=float), limits, continuous_wrist)
    pos_err = checkpoint = math.inf
    it = 0
    for it in range(1, MAX_ITERATIONS + 1):
        pos, _, jacp, _ = arm.tcp_kinematics(q)
        e_pos = position_m - pos
        pos_err = float(np.linalg.norm(e_pos)) * 1000.0
        if pos_err < _CONVERGED_MM:
            break
        if it % 10 == 0:  # stalled (against a limit, or out of reach): give up this seed
            if pos_err > 0.99 * checkpoint:
                break
            checkpoint = pos_err
        step = dls(jacp[:, :_WRIST], e_pos)
        biggest = float(np.max(np.abs(step)))
        if biggest > MAX_STEP_RAD:
            step *= MAX_STEP_RAD / biggest
        q[:_WRIST] += step
        q = _clamp(q, limits, continuous_wrist)
    roll = math.inf
    lo, hi = float(limits[_WRIST, 0]), float(limits[_WRIST, 1])
    for _ in range(3):
        pos, rot, _, jacr = arm.tcp_kinematics(q)
        roll = roll_error(rot, rot_target)
        if abs(roll) < _CONVERGED_RAD:
            break
        gain = float(rot[:, 2] @ jacr[:, _WRIST])  # roll per radian of B (+-1)
        b = q[_WRIST] + roll / gain
        if hi - lo >= 2.0 * math.pi - 1e-9 or continuous_wrist:
            b = lo + (b - lo) % (2.0 * math.pi)
        q[_WRIST] = min(max(b, lo), hi)
    pos_err = float(np.linalg.norm(position_m - pos)) * 1000.0
    return Solution(q, pos_err, roll, pos_err <= TOLERANCE_MM, it)


def solve(
    arm: Kinematics,
    pose: Sequence[float],
    q0: ArrayLike,
    limits: ArrayLike,
    continuous_wrist: bool = False,
) -> Solution:
    """Joint angles (E D C B) putting the tool centre point at `pose` (x, y, z in mm, roll,
    pitch, yaw in rad, as KM_END_POS carries it) inside `limits` (4 x 2, [min, max]); the
    best attempt, with `reachable` False if no seed got within `TOLERANCE_MM`."""
    x, y, z, r, p, w = (float(v) for v in pose)
    position = np.array([x, y, z]) / 1000.0
    rot_target = rotation_rpy(r, p, w)
    lim = np.asarray(limits, dtype=float)
    start = np.asarray(q0, dtype=float)
    facing = math.atan2(y, x) % (2.0 * math.pi)
    span = lim[:, 1] - lim[:, 0]
    grid = [(1, 1)] + [(i, j) for i in range(3) for j in range(3) if (i, j) != (1, 1)]
    seeds = [start]
    for yaw in (facing, (facing + math.pi) % (2.0 * math.pi)):
        for i, j in grid:  # D and C at 1/8, 1/2, 7/8 of their ranges, mid-range first
            d = lim[1, 0] + span[1] * (1 + 3 * i) / 8.0
            c = lim[2, 0] + span[2] * (1 + 3 * j) / 8.0
            seeds.append(np.array([yaw, d, c, start[_WRIST]]))
    best: Solution | None = None
    for seed in seeds:
        sol = refine(arm, position, rot_target, seed, lim, continuous_wrist)
        if sol.reachable:
            return sol
        if best is None or sol.position_error_mm < best.position_error_mm:
            best = sol
    assert best is not None
    return best


def joint_rates(
    arm: Kinematics,
    q: ArrayLike,
    linear_m_s: FloatArray,
    angular_rad_s: FloatArray,
    max_rates: FloatArray,
) -> FloatArray:
    """Joint rates (E D C B, rad/s) giving the tool centre point `linear_m_s` and, about the
    tool axis, the component of `angular_rad_s` along it; scaled down as a whole (so the
    direction is kept) until every joint is within `max_rates`."""
    _, rot, jacp, jacr = arm.tcp_kinematics(q)
    task = np.concatenate([linear_m_s, [ROLL_WEIGHT * float(rot[:, 2] @ angular_rad_s)]])
    rates = dls(task_jacobian(rot, jacp, jacr), task)
    over = float(np.max(np.abs(rates) / max_rates))
    return rates / over if over > 1.0 else rates


def tcp_velocity(arm: Kinematics, q: ArrayLike, qdot: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Linear (m/s) and angular (rad/s) velocity of the tool centre point, base frame."""
    _, _, jacp, jacr = arm.tcp_kinematics(q)
    qd = np.asarray(qdot, dtype=float)
    return jacp @ qd, jacr @ qd
