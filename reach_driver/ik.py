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

Where an arm reaches (`envelope`, `reach-driver workspace`), on any model's chain
(`reach_driver.drawing`): its first joint turns the whole arm about a vertical axis (the Alpha's
E through the base's origin, the Bravo's G 67.5 mm off it), so the other joints that move the
tool centre point (the Alpha's D C, the Bravo's F E D C) alone set its height and its distance
from that axis, and the first its bearing. A grid over their ranges (`GRID_STEP_RAD` apart, or
coarser to hold `GRID_POINTS`) gives each bound of the envelope and the start of the search for
a nearest point, each then polished on the chain (`_polish`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINT_LETTERS, JOINTS
from protocol.models import ALPHA5
from reach_driver.drawing import ArmDrawing, drawing_for
from reach_driver.errors import LimitError
from reach_driver.kinematics import tool_jacobian, tool_position

DAMPING = 0.01  # lambda (m)
MAX_STEP_RAD = 0.2
MAX_ITERATIONS = 150
TOLERANCE_MM = 1.0  # a target is reachable when a solution's tool centre point is this close
_CONVERGED_MM = 0.05
_ARM = 3  # E, D, C move the tool centre point; B (index 3) does not
GRID_STEP_RAD = 0.02  # the finest grid of the envelope and the nearest-point search
ALPHA5_DRAWING = drawing_for(ALPHA5)


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


#: Most poses a grid over the joints that set the tool's distance and height holds: the
#: Alpha's D and C fit at GRID_STEP_RAD (171 x 171), the Bravo's F E D C at ~0.17 rad; the
#: bounds found on the grid are then polished (`_polish`) to the chain's own.
GRID_POINTS = 250_000
#: Grid poses each bound (or nearest point) is polished from: the best few, so a coarse
#: grid's best that sits on the wrong slope does not decide alone.
_POLISH_STARTS = 4


def _reach_grid(drawing: ArmDrawing, limits: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Poses over the ranges of the joints that move the tool centre point, all but the first
    (which turns the arm about its vertical axis, `ArmDrawing.yaw_axis`): `GRID_STEP_RAD`
    apart, or coarser to hold `GRID_POINTS`, both ends included; every other joint at its
    lower limit. Returns the angles (N x joints), the tool centre points with the first joint
    at 0 (`_at_zero`: N x 3, m) and the step."""
    inner = list(drawing.positioning[1:])
    lim = limits[inner]
    span = np.maximum(lim[:, 1] - lim[:, 0], 0.0)
    step = max(
        GRID_STEP_RAD, float(np.prod(np.maximum(span, 1e-9)) / GRID_POINTS) ** (1 / len(inner))
    )
    axes = [np.linspace(lo, hi, max(2, math.ceil((hi - lo) / step) + 1)) for lo, hi in lim]
    q = np.tile(limits[:, 0], (int(np.prod([len(a) for a in axes])), 1))
    for j, values in zip(inner, np.meshgrid(*axes, indexing="ij"), strict=True):
        q[:, j] = values.ravel()
    return q, _at_zero(drawing, q), step


def _turned(
    drawing: ArmDrawing, q: np.ndarray, at_zero: np.ndarray, bearing: np.ndarray, limits: np.ndarray
) -> np.ndarray:
    """Turn poses `q` (in place) by their first joint so that each tool centre point, at
    `at_zero` (N x 3, m) with that joint at 0, lies at `bearing` (rad, about the yaw axis,
    base frame) or as near it as the joint's limits allow. Returns where the points are then."""
    centre, sense = drawing.yaw_axis
    v = at_zero[:, :2] - centre
    q[:, 0] = _bearing(sense * (bearing - np.arctan2(v[:, 1], v[:, 0])), *limits[0])
    c, s = np.cos(sense * q[:, 0]), np.sin(sense * q[:, 0])
    out = at_zero.copy()
    out[:, 0] = centre[0] + c * v[:, 0] - s * v[:, 1]
    out[:, 1] = centre[1] + s * v[:, 0] + c * v[:, 1]
    return out


def _at_zero(drawing: ArmDrawing, q: np.ndarray) -> np.ndarray:
    """The tool centre points of poses `q` with their first joint at 0 (N x 3, m)."""
    zero = np.array(q, dtype=float)
    zero[:, 0] = 0.0
    return drawing.tool_positions(zero)


def _polish(
    cost: Callable[[np.ndarray], np.ndarray],
    q: np.ndarray,
    limits: np.ndarray,
    moving: Sequence[int],
    step: float,
) -> tuple[np.ndarray, float]:
    """A pattern search from `q` for the angles of least `cost` (N poses -> N values) inside
    `limits`, moving the joints `moving`: step to the best neighbour (every combination of
    -1, 0, +1 step per joint) while one is better, else halve the step. Unlike least squares
    it only ever improves, limits or not. Returns (angles, cost)."""
    moving = list(moving)
    pattern = np.array(
        [p for p in itertools.product((-1.0, 0.0, 1.0), repeat=len(moving)) if any(p)]
    )
    best = np.asarray(q, dtype=float).copy()
    best_cost = float(cost(best[None, :])[0])
    steps = 0
    while step > 1e-6 and steps < 1000:
        steps += 1
        cand = np.repeat(best[None, :], len(pattern), axis=0)
        cand[:, moving] = np.clip(
            cand[:, moving] + step * pattern, limits[moving, 0], limits[moving, 1]
        )
        costs = cost(cand)
        k = int(np.argmin(costs))
        if costs[k] < best_cost:
            best, best_cost = cand[k], float(costs[k])
        else:
            step /= 2.0
    return best, best_cost


def _least(
    cost: Callable[[np.ndarray], np.ndarray],
    q: np.ndarray,
    costs: np.ndarray,
    limits: np.ndarray,
    moving: Sequence[int],
    step: float,
) -> tuple[np.ndarray, float]:
    """`_polish` from each of the `_POLISH_STARTS` poses of `q` of least `costs` (theirs,
    known); the best."""
    starts = np.argsort(costs)[:_POLISH_STARTS]
    found = [_polish(cost, q[k], limits, moving, step) for k in starts]
    return min(found, key=lambda f: f[1])


@dataclass(frozen=True)
class Envelope:
    """Where the tool centre point can be inside `limits` (base frame, mm): its distance from
    the axis the first joint turns the arm about (`axis_mm`, where that axis meets the base's
    x y plane), its height, and its farthest from the base's origin. The first joint sets the
    bearing, within its limits; a joint whose axis runs through the point (the wrist roll)
    never moves it. `poses`: the angles (rad, the model's joint order) at each bound."""

    limits: np.ndarray  # joints x 2 [min, max] rad
    radius_mm: tuple[float, float]
    z_mm: tuple[float, float]
    reach_mm: float
    axis_mm: tuple[float, float]
    poses: Mapping[str, np.ndarray]  # "radius_min" "radius_max" "z_min" "z_max" "reach"


def envelope(limits: np.ndarray | None = None, drawing: ArmDrawing | None = None) -> Envelope:
    """The reachable envelope of `drawing`'s arm (default the Alpha 5's) inside `limits`
    (joints x 2; default the Alpha's factory limits): the bounds on a grid of its joints
    (`_reach_grid`), each polished on the chain."""
    chain = ALPHA5_DRAWING if drawing is None else drawing
    lim = factory_limits() if limits is None else np.asarray(limits, dtype=float)
    if lim.shape != (len(chain.links), 2):
        raise ValueError(f"limits must be {len(chain.links)} x 2 [min, max], got {lim.shape}")
    centre, _ = chain.yaw_axis
    q, at_zero, step = _reach_grid(chain, lim)
    away = math.atan2(float(centre[1]), float(centre[0]))  # farthest from the origin: facing off it
    grid = _turned(chain, q.copy(), at_zero, np.full(len(q), away), lim)

    def radius(qs: np.ndarray) -> np.ndarray:  # the first joint does not change it
        return np.linalg.norm(chain.tool_positions(qs)[:, :2] - centre, axis=1)

    def height(qs: np.ndarray) -> np.ndarray:  # nor this
        return chain.tool_positions(qs)[:, 2]

    def reach(qs: np.ndarray) -> np.ndarray:
        turned = _turned(chain, qs.copy(), _at_zero(chain, qs), np.full(len(qs), away), lim)
        return np.linalg.norm(turned, axis=1)

    inner = chain.positioning[1:]
    across = np.linalg.norm(at_zero[:, :2] - centre, axis=1)
    bounds: tuple[tuple[str, Callable[[np.ndarray], np.ndarray], float, np.ndarray], ...] = (
        ("radius_min", radius, 1.0, across),
        ("radius_max", radius, -1.0, across),
        ("z_min", height, 1.0, at_zero[:, 2]),
        ("z_max", height, -1.0, at_zero[:, 2]),
        ("reach", reach, -1.0, np.linalg.norm(grid, axis=1)),
    )
    found: dict[str, tuple[np.ndarray, float]] = {}
    for name, measure, sign, known in bounds:

        def cost(qs: np.ndarray, f: Callable = measure, s: float = sign) -> np.ndarray:
            return s * f(qs)

        angles, value = _least(cost, q, sign * known, lim, inner, step)
        angles = angles[None, :].copy()
        # a pose inside the limits: the bearing that gives the bound (any, but the reach's)
        _turned(chain, angles, _at_zero(chain, angles), np.array([away]), lim)
        found[name] = (angles[0], sign * value * 1000.0)
    return Envelope(
        limits=lim,
        radius_mm=(found["radius_min"][1], found["radius_max"][1]),
        z_mm=(found["z_min"][1], found["z_max"][1]),
        reach_mm=found["reach"][1],
        axis_mm=(float(centre[0]) * 1000.0, float(centre[1]) * 1000.0),
        poses=MappingProxyType({k: v[0] for k, v in found.items()}),
    )


def _bearing(want: np.ndarray, low: float, high: float) -> np.ndarray:
    """Angles of the first joint nearest `want` (rad, any turn) inside [low, high]."""
    a = np.mod(want, 2.0 * math.pi)
    out = np.clip(a, low, high)
    outside = (a < low) | (a > high)
    # outside the range: the nearer end, going round either way
    to_low = np.mod(low - a, 2.0 * math.pi)
    to_high = np.mod(a - high, 2.0 * math.pi)
    return np.where(outside, np.where(to_low <= to_high, low, high), out)


def nearest_on_grid(
    drawing: ArmDrawing, target_m: np.ndarray, q0: np.ndarray, limits: np.ndarray
) -> tuple[np.ndarray, float]:
    """The angles putting `drawing`'s tool centre point nearest `target_m` inside `limits`,
    searched over the whole workspace: the grid's poses (`_reach_grid`), each turned to the
    target's bearing about the yaw axis (or the nearest the first joint's limits allow), the
    best polished; the joints that do not move the point keep q0's. (angles, distance mm)."""
    q, at_zero, step = _reach_grid(drawing, limits)
    fixed = [i for i in range(len(drawing.links)) if i not in drawing.positioning]
    q[:, fixed] = np.asarray(q0, dtype=float)[fixed]
    centre, _ = drawing.yaw_axis
    toward = math.atan2(float(target_m[1] - centre[1]), float(target_m[0] - centre[0]))
    points = _turned(drawing, q, at_zero, np.full(len(q), toward), limits)

    def gap(qs: np.ndarray) -> np.ndarray:
        return np.linalg.norm(drawing.tool_positions(qs) - target_m, axis=1)

    known = np.linalg.norm(points - target_m, axis=1)
    angles, metres = _least(gap, q, known, limits, drawing.positioning, step)
    return angles, metres * 1000.0


def nearest_reachable(
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray | None = None,
) -> Solution:
    """`solve_position`'s solution if the target is reachable; otherwise the angles putting
    the tool centre point nearest to it inside `limits` (`nearest_on_grid`; B kept at q0's)."""
    sol = solve_position(xyz_mm, q0, limits)
    if sol.reachable:
        return sol
    lim = factory_limits() if limits is None else np.asarray(limits, dtype=float)
    target = np.asarray(xyz_mm, dtype=float) / 1000.0
    start = np.asarray(q0, dtype=float).reshape(-1)
    angles, error_mm = nearest_on_grid(ALPHA5_DRAWING, target, start, lim)
    return min((sol, Solution(angles, error_mm, 0)), key=lambda s: s.error_mm)


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


# -- another model's chain (`reach_driver.drawing`) -------------------------------------------
#
# The Bravo 7 has five joints that move the tool centre point (G F E D C; B turns the tool
# about its axis) for three coordinates: redundant. The same damped least squares, on all five
# with a Jacobian by finite differences of the chain generated from the MJCF, steps from the
# present angles by the least joint motion each time; then from seeds facing the target (and
# away), the shoulder and elbow across their ranges, the wrist as it is. What no start reaches
# within TOLERANCE_MM is out of reach: the whole workspace is searched for the nearest point
# (`nearest_on_grid`), as the Alpha's is.


@dataclass(frozen=True)
class ChainSolution:
    """A solution on another model's chain: angles in its joint order, the tool centre point
    they give (mm) and its distance from the target."""

    q: np.ndarray
    point_mm: np.ndarray
    error_mm: float

    @property
    def reachable(self) -> bool:
        return self.error_mm <= TOLERANCE_MM


def _chain_jacobian(drawing: ArmDrawing, q: np.ndarray, moving: Sequence[int]) -> np.ndarray:
    """3 x len(moving) position Jacobian (m/rad) by central differences."""
    h = 1e-6
    cols = []
    for i in moving:
        up, down = q.copy(), q.copy()
        up[i] += h
        down[i] -= h
        cols.append((drawing.tool_position(up) - drawing.tool_position(down)) / (2.0 * h))
    return np.stack(cols, axis=1)


def _refine_chain(
    drawing: ArmDrawing, target_m: np.ndarray, q0: np.ndarray, limits: np.ndarray
) -> ChainSolution:
    moving = list(drawing.positioning)
    q = np.clip(np.asarray(q0, dtype=float), limits[:, 0], limits[:, 1])
    checkpoint = math.inf
    for it in range(1, MAX_ITERATIONS + 1):
        e = target_m - drawing.tool_position(q)
        err_mm = float(np.linalg.norm(e)) * 1000.0
        if err_mm < _CONVERGED_MM:
            break
        if it % 10 == 0:
            if err_mm > 0.99 * checkpoint:
                break
            checkpoint = err_mm
        j = _chain_jacobian(drawing, q, moving)
        step = j.T @ np.linalg.solve(j @ j.T + DAMPING * DAMPING * np.eye(3), e)
        biggest = float(np.max(np.abs(step)))
        if biggest > MAX_STEP_RAD:
            step *= MAX_STEP_RAD / biggest
        q[moving] = np.clip(q[moving] + step, limits[moving, 0], limits[moving, 1])
    point = drawing.tool_position(q) * 1000.0
    return ChainSolution(q, point, float(np.linalg.norm(point - target_m * 1000.0)))


def solve_on_chain(
    drawing: ArmDrawing,
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray,
) -> ChainSolution:
    """Angles (the model's order) putting the tool centre point of `drawing`'s arm at `xyz_mm`
    (base frame, mm) inside `limits` (n x 2), from `q0`; the best attempt (check
    `reachable`)."""
    target = np.asarray(xyz_mm, dtype=float).reshape(-1)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise ValueError(f"target must be 3 finite numbers x y z in mm, got {xyz_mm!r}")
    start = np.asarray(q0, dtype=float).reshape(-1)
    lim = np.asarray(limits, dtype=float)
    if start.shape != (len(drawing.links),) or not np.all(np.isfinite(start)):
        raise ValueError(f"start angles must be {len(drawing.links)} finite numbers, got {q0!r}")
    target_m = target / 1000.0
    starts = [start]
    facing = math.atan2(float(target_m[1]), float(target_m[0]))
    span = lim[:, 1] - lim[:, 0]
    for yaw in (facing, facing + math.pi):
        for i, j in ((1, 1), (0, 1), (2, 1), (1, 0), (1, 2)):
            seed = start.copy()
            seed[0] = _bearing(np.array(yaw), *lim[0])
            seed[1] = lim[1, 0] + span[1] * (1 + 3 * i) / 8.0
            seed[2] = lim[2, 0] + span[2] * (1 + 3 * j) / 8.0
            starts.append(seed)
    best: ChainSolution | None = None
    for seed in starts:
        sol = _refine_chain(drawing, target_m, seed, lim)
        if sol.reachable:
            return sol
        if best is None or sol.error_mm < best.error_mm:
            best = sol
    assert best is not None
    return best


def nearest_on_chain(
    drawing: ArmDrawing,
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray,
) -> ChainSolution:
    """`solve_on_chain`'s solution if the target is reachable; otherwise the angles putting
    the tool centre point nearest to it inside `limits` (`nearest_on_grid`)."""
    sol = solve_on_chain(drawing, xyz_mm, q0, limits)
    if sol.reachable:
        return sol
    target_m = np.asarray(xyz_mm, dtype=float) / 1000.0
    lim = np.asarray(limits, dtype=float)
    angles, error_mm = nearest_on_grid(drawing, target_m, np.asarray(q0, dtype=float), lim)
    if error_mm >= sol.error_mm:
        return sol
    return ChainSolution(angles, drawing.tool_position(angles) * 1000.0, error_mm)


def nearest_on(
    drawing: ArmDrawing,
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray,
) -> Solution | ChainSolution:
    """The angles for a tool position on `drawing`'s arm, or the nearest reachable point's:
    the Alpha 5 by its own chain's solver (`nearest_reachable`), another by its drawing's
    (`nearest_on_chain`)."""
    if drawing is ALPHA5_DRAWING:
        return nearest_reachable(xyz_mm, q0, limits)
    return nearest_on_chain(drawing, xyz_mm, q0, limits)


def solve_on_chain_or_refuse(
    drawing: ArmDrawing,
    letters: Sequence[str],
    xyz_mm: Sequence[float],
    q0: Sequence[float] | np.ndarray,
    limits: np.ndarray,
) -> np.ndarray:
    """`nearest_on_chain`'s angles, or `UnreachableError` naming the nearest reachable point,
    its angles and how far it is."""
    sol = nearest_on_chain(drawing, xyz_mm, q0, limits)
    if sol.reachable:
        return sol.q
    angles = " ".join(f"{j} {v:.3f}" for j, v in zip(letters, sol.q, strict=True))
    raise UnreachableError(
        f"refused: tool target {xyz_text(xyz_mm)} mm is out of reach inside the position "
        f"limits; the nearest reachable point is {xyz_text(sol.point_mm)} mm, "
        f"{sol.error_mm:.1f} mm away, at {angles} rad (`reach-driver workspace` shows the "
        "whole envelope); nothing was sent",
        sol.error_mm,
        sol.q,
        sol.point_mm,
    )
