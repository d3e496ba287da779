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
limits: `nearest_reachable` then searches the whole workspace for the point nearest to it, and
`UnreachableError` names that point, its angles and its distance.

Where the arm reaches (`envelope`, `reach-driver workspace`): the tool centre point always lies
in the vertical plane through the base's axis that E turns (D and C rotate about axes normal to
it; B's axis runs through the point). So D and C alone set its height and its distance from the
base's axis, and E its bearing: a grid over D and C's ranges, `GRID_STEP_RAD` apart, gives both
the envelope and the start of the search for a nearest point.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINT_LETTERS, JOINTS
from reach_driver.errors import LimitError
from reach_driver.kinematics import tool_jacobian, tool_position, tool_positions

DAMPING = 0.01  # lambda (m)
MAX_STEP_RAD = 0.2
MAX_ITERATIONS = 150
TOLERANCE_MM = 1.0  # a target is reachable when a solution's tool centre point is this close
_CONVERGED_MM = 0.05
_ARM = 3  # E, D, C move the tool centre point; B (index 3) does not
GRID_STEP_RAD = 0.02  # D and C, for the envelope and the nearest-point search


class UnreachableError(LimitError):
    """No joint angles inside the position limits put the tool centre point at the target;
    nothing was sent. `distance_mm` is how far the nearest reachable point is."""

    def __init__(
        self, message: str, distance_mm: float, best: np.ndarray, nearest_mm: np.ndarray
    ) -> None:
        super().__init__(message)
        self.distance_mm = distance_mm
        self.best = best  # the nearest reachable point's angles E D C B (rad)
        self.nearest_mm = nearest_mm  # that point, x y z (mm, base frame)


@dataclass(frozen=True)
class Solution:
    q: np.ndarray  # E D C B (rad)
    error_mm: float  # distance of its tool centre point from the target
    iterations: int

    @property
    def reachable(self) -> bool:
        return self.error_mm <= TOLERANCE_MM

    @property
    def point_mm(self) -> np.ndarray:
        """Where these angles put the tool centre point (x y z, mm)."""
        return tool_position(self.q) * 1000.0


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


def _plane_grid(limits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """D and C over their ranges (`GRID_STEP_RAD` apart, both ends included) and where each
    pair puts the tool centre point in E's plane: (D C pairs, u, w), u (m) along the arm's
    bearing (negative: leaning back over the base), w (m) the height."""
    axes = [
        np.linspace(lo, hi, max(2, math.ceil((hi - lo) / GRID_STEP_RAD) + 1))
        for lo, hi in limits[1:_ARM]
    ]
    d, c = (a.ravel() for a in np.meshgrid(*axes, indexing="ij"))
    q = np.zeros((len(d), len(JOINTS)))
    q[:, 1], q[:, 2] = d, c
    p = tool_positions(q)  # E = 0: the plane is x z
    return np.stack([d, c], axis=1), p[:, 0], p[:, 2]


@dataclass(frozen=True)
class Envelope:
    """Where the tool centre point can be inside `limits` (base frame, mm): its horizontal
    distance from the base's axis, its height, and its farthest from the base's origin. E
    sets the bearing, within its limits; B never moves the point."""

    limits: np.ndarray  # 4 x 2 [min, max] rad, E D C B
    radius_mm: tuple[float, float]
    z_mm: tuple[float, float]
    reach_mm: float


def envelope(limits: np.ndarray | None = None) -> Envelope:
    """The reachable envelope inside `limits` (default the factory limits)."""
    lim = factory_limits() if limits is None else np.asarray(limits, dtype=float)
    _, u, w = _plane_grid(lim)
    r, z = np.abs(u) * 1000.0, w * 1000.0
    return Envelope(
        limits=lim,
        radius_mm=(float(r.min()), float(r.max())),
        z_mm=(float(z.min()), float(z.max())),
        reach_mm=float(np.sqrt(r * r + z * z).max()),
    )


def _bearing(want: np.ndarray, low: float, high: float) -> np.ndarray:
    """E angles nearest `want` (rad, any turn) inside [low, high]."""
    a = np.mod(want, 2.0 * math.pi)
    out = np.clip(a, low, high)
    outside = (a < low) | (a > high)
    # outside the range: the nearer end, going round either way
    to_low = np.mod(low - a, 2.0 * math.pi)
    to_high = np.mod(a - high, 2.0 * math.pi)
    return np.where(outside, np.where(to_low <= to_high, low, high), out)


def nearest_reachable(
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray | None = None,
) -> Solution:
    """`solve_position`'s solution if the target is reachable; otherwise the angles putting
    the tool centre point nearest to it inside `limits`: the best grid point over the whole
    workspace (E at the bearing nearest the target's), refined (B kept at q0's)."""
    sol = solve_position(xyz_mm, q0, limits)
    if sol.reachable:
        return sol
    lim = factory_limits() if limits is None else np.asarray(limits, dtype=float)
    target = np.asarray(xyz_mm, dtype=float) / 1000.0
    dc, u, w = _plane_grid(lim)
    facing = math.atan2(float(target[1]), float(target[0]))
    e = _bearing(np.where(u >= 0.0, facing, facing + math.pi), *lim[0])
    gap = (u * np.cos(e) - target[0]) ** 2 + (u * np.sin(e) - target[1]) ** 2
    gap += (w - target[2]) ** 2
    k = int(np.argmin(gap))
    seed = np.array([e[k], dc[k, 0], dc[k, 1], np.asarray(q0, dtype=float).reshape(-1)[_ARM]])
    return min((sol, _polish(target, seed, lim)), key=lambda s: s.error_mm)


#: E D C offsets of a pattern search step: every combination of -1, 0, +1 but all zeros.
_PATTERN = np.array(
    [
        (a, b, c)
        for a in (-1, 0, 1)
        for b in (-1, 0, 1)
        for c in (-1, 0, 1)
        if (a, b, c) != (0, 0, 0)
    ],
    dtype=float,
)


def _polish(target_m: np.ndarray, q: np.ndarray, limits: np.ndarray) -> Solution:
    """A pattern search from `q` for the angles nearest `target_m` inside `limits` (E D C;
    B kept): step to the best neighbour while one is nearer, else halve the step. Unlike
    `refine`'s least squares it only ever gets nearer, limits or not."""
    best = q.copy()
    best_m = float(np.linalg.norm(tool_position(best) - target_m))
    step = GRID_STEP_RAD
    steps = 0
    while step > 1e-6 and steps < 1000:
        steps += 1
        cand = np.repeat(best[None, :], len(_PATTERN), axis=0)
        cand[:, :_ARM] = np.clip(
            cand[:, :_ARM] + step * _PATTERN, limits[:_ARM, 0], limits[:_ARM, 1]
        )
        gaps = np.linalg.norm(tool_positions(cand) - target_m, axis=1)
        k = int(np.argmin(gaps))
        if gaps[k] < best_m:
            best, best_m = cand[k], float(gaps[k])
        else:
            step /= 2.0
    return Solution(best, best_m * 1000.0, steps)


def xyz_text(xyz_mm: Sequence[float] | np.ndarray) -> str:
    """'(344.5, 0.0, 39.3)': a point in mm to 0.1 mm (no '-0.0')."""
    return "(" + ", ".join(f"{round(float(v), 1) + 0.0:.1f}" for v in xyz_mm) + ")"


def angles_text(q: np.ndarray) -> str:
    """'E 3.100 D 1.500 C 1.500 B 3.142 rad'."""
    return " ".join(f"{j} {v:.3f}" for j, v in zip(JOINT_LETTERS, q, strict=True)) + " rad"


def solve_or_refuse(
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray | None = None,
) -> np.ndarray:
    """`solve_position`'s angles, or `UnreachableError` naming the target and the nearest
    reachable point: where it is, its angles and how far it is."""
    sol = nearest_reachable(xyz_mm, q0, limits)
    if sol.reachable:
        return sol.q
    raise UnreachableError(
        f"refused: tool target {xyz_text(xyz_mm)} mm is out of reach inside the position "
        f"limits; the nearest reachable point is {xyz_text(sol.point_mm)} mm, "
        f"{sol.error_mm:.1f} mm away, at {angles_text(sol.q)} (`reach-driver workspace` "
        "shows the whole envelope); nothing was sent",
        sol.error_mm,
        sol.q,
        sol.point_mm,
    )
