"""The replay that scores a parameter set: the logged commands run open loop through the twin
(`Replay`, multiple shooting over windows), parameter references (`ParamRef`) and the
prediction quality (`quality`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocol.alpha5 import JOINT_LETTERS, N_JOINTS
from reach_sim_bridge.fit.segments import MAX_DELAY_S, FloatArray, Segment
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams

DELAY = "delay_s"
"""The name of the transport-delay parameter (not an `ArmParams` field)."""

DEFAULT_WINDOW_S = 1.0
VELOCITY_WEIGHT_S = 0.02
"""Velocity residuals (rad/s) are weighted by this (s) next to position residuals (rad)."""
ROBUST_CLIP = 3.0
"""`Replay.window_weights`: windows worse than this times the median window are down-weighted."""
STALL_S = 0.02
"""A command measured later than this after its tick (s) cuts the replay's window there."""
PLAN_CACHE = 256  # command schedules kept by `Replay` (per segment and delay)
PRUNE_MARGIN = 1e-9
"""`Replay.cost` stops a replay once its partial sum exceeds the bound by this (relative):
summed in another order than `r @ r`, it may differ from it by ~1e-12 at most."""
SKIP_TICKS = 3
"""Ticks at the start of a segment not used: the joints leave position mode there."""

#: Per tick, runs of (current held, physics steps): how `Replay` drives the arm.
Schedule = list[list[tuple[FloatArray, int]]]
#: A parameter: (ArmParams field, joint index) or (DELAY, -1).
ParamRef = tuple[str, int]


@dataclass(frozen=True)
class Rollout:
    """The twin's prediction of a segment: NaN where no prediction (window starts)."""

    q: FloatArray
    qdot: FloatArray
    window: NDArray[np.int64] | None = None  # per row: the window that predicted it, or -1


def schedule_key(plan: Schedule) -> bytes:
    """`plan`'s content as bytes: two schedules with one key drive the arm alike (a replay's
    rollout depends on its schedule, not on the delay that made it)."""
    out = bytearray()
    for runs in plan:
        out += len(runs).to_bytes(4, "little")
        for current, steps in runs:
            out += np.asarray(current, dtype=np.float64).tobytes()
            out += int(steps).to_bytes(4, "little")
    return bytes(out)


def params_with(base: ArmParams, refs: Sequence[ParamRef], values: Sequence[float]) -> ArmParams:
    """`base` with the `ArmParams` entries named by `refs` set (the delay is skipped)."""
    changes: dict[str, list[float]] = {}
    for (name, index), value in zip(refs, values, strict=True):
        if name == DELAY:
            continue
        vec = changes.setdefault(name, list(getattr(base, name)))
        vec[index] = float(value)
    fields: dict[str, Any] = {k: tuple(v) for k, v in changes.items()}
    return replace(base, **fields)


def with_payload(params: ArmParams, seg: Segment) -> ArmParams:
    """`params` holding the load `seg` was logged with (the fitted arm itself holds none)."""
    if (params.payload_kg, params.payload_volume_l) == (seg.payload_kg, seg.payload_volume_l):
        return params
    return replace(params, payload_kg=seg.payload_kg, payload_volume_l=seg.payload_volume_l)


def param_value(params: ArmParams, delay_s: float, ref: ParamRef) -> float:
    name, index = ref
    return float(delay_s) if name == DELAY else float(getattr(params, name)[index])


def ref_name(ref: ParamRef) -> str:
    name, index = ref
    return name if name == DELAY else f"{name}[{JOINT_LETTERS[index]}]"


class Replay:
    """Replays logged segments on one `Alpha5Arm` (reused across parameter sets)."""

    def __init__(
        self,
        base: ArmParams | None = None,
        dt: float = 0.002,
        window_s: float = DEFAULT_WINDOW_S,
        teacher_force: bool = True,
        quantum_s: float = 0.0,
        stall_s: float = STALL_S,
        coast_others: bool = True,
    ) -> None:
        self.arm = Alpha5Arm(params=base, dt=dt)
        # With `teacher_force`, the joints not excited coast between the ticks that put them
        # on their path (`Alpha5Arm.coast`) instead of moving under their logged currents.
        # Driven, they moved as the twin's values for *them* said: a weak D (25 % torque)
        # holding the arm on 175-240 mA moved four times too hard under a nominal D between
        # ticks, and C's fit, made before D's, took the reaction (docs/identification.md).
        self.coast_others = coast_others
        self.quantum_s = float(quantum_s)
        self.stall_s = float(stall_s)
        self.window_s = window_s
        self.teacher_force = teacher_force
        self.rollouts = 0
        # (commands, delays, offset, period, delay) -> schedule: the fit scores many parameter
        # sets (and window starts: copies of one segment) at one delay; the arrays are kept
        # beside it so their ids cannot be reused while cached.
        self._plans: dict[tuple[int, int, float, float, float], tuple[Any, Any, Schedule]] = {}

    def schedule(self, seg: Segment, delay_s: float) -> list[list[tuple[FloatArray, int]]]:
        """The currents the arm held over each tick of `seg`: per tick, runs of (current, physics
        steps). Command row i (sent at tick i-1) lands at t[i-1] + its delay, the delay being
        `delay_s` plus the segment's measured `link_delay_s` (if any), clipped to
        [0, MAX_DELAY_S]; it is held until the next one lands (a serial link keeps the order).
        A physics step in which a command lands gets the time-weighted mean of the currents
        it held, so rollouts are continuous in the delay."""
        period, dt = seg.period, self.arm.dt
        substeps = int(round(period / dt))
        if abs(substeps * dt - period) > 1e-9 or substeps < 1:
            raise ValueError(f"segment period {period} s is not a whole number of {dt} s steps")
        n = seg.ticks
        cmd = seg.command_mA
        delays = np.full(n + 1, float(delay_s) + seg.offset_s)
        held = np.zeros(n + 1, dtype=bool)
        if seg.link_delay_s is not None:
            held = ~np.isfinite(seg.link_delay_s)
            delays[1:] += np.where(held[1:], 0.0, seg.link_delay_s[1:])
        delays = np.clip(delays, 0.0, MAX_DELAY_S)
        # arrival[r - 1]: when row r (1..n) lands; before the first landing row 1 is held.
        arrival = np.arange(n) * period + delays[1:]
        # A row no command was sent for holds the one before: it "lands" with it.
        for row in (np.flatnonzero(held[2:]) + 2).tolist():
            arrival[row - 1] = arrival[row - 2]
        if self.quantum_s > 0:
            # The arm acts on a command from the start of its own control step in which the
            # command came in (the virtual arm steps its physics lazily, 2 ms at a time).
            arrival = np.floor(arrival / self.quantum_s + 1e-9) * self.quantum_s
        arrival = np.maximum.accumulate(arrival)
        bounds = (np.arange(n * substeps + 1) / substeps) * period
        first_row = np.maximum(np.searchsorted(arrival, bounds[:-1], side="right"), 1)
        last_row = np.maximum(np.searchsorted(arrival, bounds[1:], side="left"), 1)
        out: Schedule = []
        for k in range(n):
            runs: list[tuple[FloatArray, int]] = []
            run_row, run_len = -1, 0
            for m in range(k * substeps, (k + 1) * substeps):
                r0, r1 = int(first_row[m]), int(last_row[m])
                if r0 == r1:
                    if r0 == run_row:
                        run_len += 1
                        continue
                    if run_len:
                        runs.append((cmd[run_row], run_len))
                    run_row, run_len = r0, 1
                    continue
                if run_len:
                    runs.append((cmd[run_row], run_len))
                run_row, run_len = -1, 0
                lo, hi = bounds[m], bounds[m + 1]
                mixed = np.zeros(N_JOINTS)
                for r in range(r0, r1 + 1):
                    start = lo if r == r0 else max(lo, arrival[r - 1])
                    stop = hi if r == r1 else min(hi, arrival[r])
                    mixed += max(stop - start, 0.0) * cmd[r]
                runs.append((mixed / (hi - lo), 1))
            if run_len:
                runs.append((cmd[run_row], run_len))
            out.append(runs)
        return out

    def windows(self, seg: Segment, w_ticks: int) -> list[tuple[int, int]]:
        """The (start, end) ticks of each multiple-shooting window: every `w_ticks` from the
        first usable tick, and, when windowed, cut where the link stalled (a command whose
        measured delay exceeds `stall_s`, or a tick the loop skipped): the window ends at the
        tick before and the next starts from the state measured once the late command has
        landed. Why: on a loaded host the arm's side may have stalled too (the virtual arm
        then catches up in a burst), which no timestamp on the host shows. Windows depend on
        the measured data only, so every candidate parameter set and offset is scored on the
        same samples (the residual keeps its length while the fit moves them)."""
        n, period = seg.ticks, seg.period
        first = SKIP_TICKS + int(math.ceil(MAX_DELAY_S / period - 1e-12))
        d = seg.link_delay_s
        if d is None or self.stall_s <= 0 or w_ticks >= n:
            return [(s, min(s + w_ticks, n)) for s in range(first, n, w_ticks)]
        bad = ~np.isfinite(d) | (np.nan_to_num(d, nan=0.0) > self.stall_s)
        bad[0] = False
        out: list[tuple[int, int]] = []
        s = first
        while s < n:
            end = min(s + w_ticks, n)
            hit = np.flatnonzero(bad[s + 1 : end + 1])
            if hit.size == 0:
                out.append((s, end))
                s = end
                continue
            r = s + 1 + int(hit[0])  # row r acts over tick r-1 .. r
            if r - 1 > s:
                out.append((s, r - 1))
            late = float(d[r]) if math.isfinite(d[r]) else period
            s = max(r - 1 + int(math.ceil(late / period - 1e-9)) + 1, s + 1)
        return out

    def window_ticks(self, seg: Segment, window_s: float | None = None) -> int:
        """Ticks per window; ``window_s`` <= 0 or inf: the whole segment."""
        window = self.window_s if window_s is None else window_s
        if not (window > 0 and math.isfinite(window)):
            return seg.ticks
        return max(1, int(round(window / seg.period)))

    def residual_windows(
        self, segments: Sequence[Segment], velocity_weight: float = VELOCITY_WEIGHT_S
    ) -> NDArray[np.int64]:
        """The window (numbered across `segments` in order) each row of `residuals` belongs
        to: the fit's Jacobian in the window starts is one column per window, and a window's
        start moves that window's rows only."""
        out: list[NDArray[np.int64]] = []
        base = 0
        for seg in segments:
            spans = self.windows(seg, self.window_ticks(seg))
            rows = np.concatenate(
                [np.full(end - s, base + w, dtype=np.int64) for w, (s, end) in enumerate(spans)]
            )
            out.append(rows)
            if velocity_weight > 0:
                out.append(rows)
            if seg.start_fix is not None:
                ids = base + np.arange(len(spans), dtype=np.int64)
                out.extend([ids, ids])
            base += len(spans)
        return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)

    def with_starts(self, segments: Sequence[Segment]) -> list[Segment]:
        """`segments`, each with window starts to fit (zero, unless it has its own)."""
        return [
            s
            if s.start_fix is not None
            else replace(s, start_fix=np.zeros((len(self.windows(s, self.window_ticks(s))), 2)))
            for s in segments
        ]

    def plan(self, seg: Segment, delay_s: float) -> Schedule:
        """The `schedule` a replay of `seg` at `delay_s` runs, kept for the next (`_plans`)."""
        key = (
            id(seg.command_mA),
            id(seg.link_delay_s),
            seg.offset_s,
            seg.period,
            float(delay_s),
        )
        cached = self._plans.get(key)
        if cached is None or cached[0] is not seg.command_mA or cached[1] is not seg.link_delay_s:
            if len(self._plans) >= PLAN_CACHE:
                self._plans.pop(next(iter(self._plans)))
            plan_new = self.schedule(seg, delay_s)
            cached = self._plans[key] = (seg.command_mA, seg.link_delay_s, plan_new)
        return cached[2]

    def simulate(
        self, params: ArmParams, delay_s: float, seg: Segment, window_s: float | None = None
    ) -> Rollout:
        """The twin `params` driven by the segment's commands (see the module docstring).
        ``window_s`` <= 0 or inf: one window from the first usable tick to the end."""
        rollout = self._simulate(params, delay_s, seg, window_s)
        assert rollout is not None  # nothing to stop it
        return rollout

    def _simulate(
        self,
        params: ArmParams,
        delay_s: float,
        seg: Segment,
        window_s: float | None = None,
        stop: Callable[[int, int, FloatArray, FloatArray], bool] | None = None,
    ) -> Rollout | None:
        """`simulate`; with `stop`, asked after each window (its first and last tick, the
        rollout so far) whether to go on: None once it says stop."""
        arm = self.arm
        arm.set_params(with_payload(params, seg))
        self.rollouts += 1
        w_ticks = self.window_ticks(seg, window_s)
        plan = self.plan(seg, delay_s)
        spans = self.windows(seg, w_ticks)
        fix = seg.start_fix
        if fix is not None and fix.shape[0] != len(spans):
            raise ValueError(
                f"segment {seg.name}: start_fix has {fix.shape[0]} rows for {len(spans)} "
                "windows (fitted on other windows)"
            )
        q_out = np.full_like(seg.q, np.nan)
        qd_out = np.full_like(seg.qdot, np.nan)
        others = [i for i in range(N_JOINTS) if i != seg.joint]
        if self.teacher_force and self.coast_others:
            arm.coast(others)
        data = arm.data
        win = np.full(seg.q.shape[0], -1, dtype=np.int64)
        for w, (s, end) in enumerate(spans):
            win[s + 1 : end + 1] = w
            q0, qd0 = seg.q[s], seg.qdot[s]
            if fix is not None:
                q0, qd0 = q0.copy(), qd0.copy()
                q0[seg.joint] += fix[w, 0]
                qd0[seg.joint] += fix[w, 1]
            arm.reset(q=q0, qdot=qd0)
            for k in range(s, end):
                if self.teacher_force and k > s:
                    for i in others:
                        data.qpos[i] = seg.q[k, i]
                        data.qvel[i] = seg.qdot[k, i]
                for current, steps in plan[k]:
                    arm.step(current, n=steps)
                q_out[k + 1] = arm.q
                qd_out[k + 1] = arm.qdot
            if stop is not None and stop(s, end, q_out, qd_out):
                return None
        return Rollout(q_out, qd_out, win)

    def residuals(
        self,
        params: ArmParams,
        delay_s: float,
        segments: Sequence[Segment],
        velocity_weight: float = VELOCITY_WEIGHT_S,
        window_s: float | None = None,
    ) -> FloatArray:
        """Position (rad) and weighted velocity residuals of each segment's excited joint;
        where the segment has fitted window starts, each start's departure from its reading
        too (the reading is one more measurement, weighted as the rest)."""
        parts = []
        for seg in segments:
            r = self.simulate(params, delay_s, seg, window_s)
            parts.extend(self._residual_parts(r, seg, velocity_weight))
        return np.concatenate(parts) if parts else np.zeros(0)

    @staticmethod
    def _joint_residuals(
        q: FloatArray,
        qd: FloatArray,
        seg: Segment,
        velocity_weight: float,
        rows: slice = slice(None),
    ) -> list[FloatArray]:
        """The excited joint's position and weighted velocity residuals over `rows`, where
        the replay has a value: what `residuals` and `cost`'s running sum both count."""
        j = seg.joint
        ok = np.isfinite(q[rows, j])
        parts = [q[rows, j][ok] - seg.q[rows, j][ok]]
        if velocity_weight > 0:
            parts.append(velocity_weight * (qd[rows, j][ok] - seg.qdot[rows, j][ok]))
        return parts

    @staticmethod
    def _residual_parts(r: Rollout, seg: Segment, velocity_weight: float) -> list[FloatArray]:
        """One segment's share of `residuals`, from its rollout."""
        parts = Replay._joint_residuals(r.q, r.qdot, seg, velocity_weight)
        if seg.start_fix is not None:
            parts.append(seg.start_fix[:, 0])
            parts.append(velocity_weight * seg.start_fix[:, 1])
        return parts

    def cost(
        self,
        params: ArmParams,
        delay_s: float,
        segments: Sequence[Segment],
        velocity_weight: float = VELOCITY_WEIGHT_S,
        above: float = math.inf,
    ) -> float:
        """The squared sum of `residuals` (as `r @ r`, to the last bit); or inf as soon as the
        windows replayed so far already cost more than `above` (with a margin far over the
        rounding), the rest left unreplayed. Why: a search for the lowest cost (the coarse
        start's grid, the delay offsets' grid) needs no more of a point than that it is not
        the lowest, and most points are far off from their first window on; the points it
        keeps, and their costs, are the same."""
        limit = above * (1.0 + PRUNE_MARGIN) if math.isfinite(above) else math.inf
        spent = 0.0
        parts: list[FloatArray] = []
        for seg in segments:
            if seg.start_fix is not None:
                fix = seg.start_fix
                spent += float(fix[:, 0] @ fix[:, 0])
                spent += velocity_weight**2 * float(fix[:, 1] @ fix[:, 1])

            def over(s: int, end: int, q: FloatArray, qd: FloatArray, seg: Segment = seg) -> bool:
                nonlocal spent
                rows = slice(s + 1, end + 1)  # the window just replayed
                for part in self._joint_residuals(q, qd, seg, velocity_weight, rows):
                    spent += float(part @ part)
                return spent > limit

            r = self._simulate(params, delay_s, seg, None, over if limit < math.inf else None)
            if r is None:
                return math.inf
            parts.extend(self._residual_parts(r, seg, velocity_weight))
        res = np.concatenate(parts) if parts else np.zeros(0)
        return float(res @ res)

    def window_errors(
        self, params: ArmParams, delay_s: float, segments: Sequence[Segment]
    ) -> list[tuple[NDArray[np.int64], dict[int, float]]]:
        """Per segment: the window of each residual row, and each window's RMS angle error."""
        out = []
        for seg in segments:
            r = self.simulate(params, delay_s, seg)
            j = seg.joint
            ok = np.isfinite(r.q[:, j])
            err = r.q[ok, j] - seg.q[ok, j]
            win = r.window[ok] if r.window is not None else np.zeros(err.size, dtype=np.int64)
            rms = {int(w): float(np.sqrt(np.mean(err[win == w] ** 2))) for w in np.unique(win)}
            out.append((win, rms))
        return out

    def median_window_rms(
        self, params: ArmParams, delay_s: float, segments: Sequence[Segment]
    ) -> float:
        """The median window's RMS angle error: what most of the data says, whatever a few
        stalled windows do."""
        values = [
            v for _, rms in self.window_errors(params, delay_s, segments) for v in rms.values()
        ]
        return float(np.median(values)) if values else math.inf

    def window_weights(
        self,
        params: ArmParams,
        delay_s: float,
        segments: Sequence[Segment],
        velocity_weight: float = VELOCITY_WEIGHT_S,
        clip: float = ROBUST_CLIP,
    ) -> FloatArray:
        """Weights for `residuals` (same layout): 1 for a window whose RMS angle error on
        `params` is within `clip` times the median window's, less for worse ones (down to
        clip x median / RMS: a Huber weight per window). Why: a window in which the arm's
        side stalled unseen is replayed wrong whatever the parameters, and least squares
        would bend the parameters to it."""
        per_seg = self.window_errors(params, delay_s, segments)
        rms_all = [v for _, rms in per_seg for v in rms.values()]
        if not rms_all:
            return np.zeros(0)
        limit = clip * max(float(np.median(rms_all)), 1e-12)
        parts = []
        for seg, (win, rms) in zip(segments, per_seg, strict=True):
            w = np.array([min(1.0, limit / max(rms[int(x)], 1e-15)) for x in win])
            parts.append(w)
            if velocity_weight > 0:
                parts.append(w)
            if seg.start_fix is not None:
                starts = np.array([min(1.0, limit / max(rms[k], 1e-15)) for k in sorted(rms)])
                parts.extend([starts, starts])
        return np.concatenate(parts)


@dataclass(frozen=True)
class Quality:
    """How well a twin predicts segments: the excited joint's angle."""

    r2: float
    rms_rad: float
    r2_velocity: float
    rms_velocity: float
    samples: int

    def as_dict(self) -> dict[str, float]:
        return {
            "r2": self.r2,
            "rms_mrad": self.rms_rad * 1e3,
            "r2_velocity": self.r2_velocity,
            "rms_velocity_rad_s": self.rms_velocity,
            "samples": self.samples,
        }


def quality(
    replay: Replay,
    params: ArmParams,
    delay_s: float,
    segments: Sequence[Segment],
    window_s: float | None = None,
) -> Quality:
    """R^2 and RMS of the excited joint's predicted angle and speed over `segments` (R^2
    against each segment's own mean)."""
    res_q, tot_q, res_v, tot_v = [], [], [], []
    for seg in segments:
        r = replay.simulate(params, delay_s, seg, window_s)
        j = seg.joint
        ok = np.isfinite(r.q[:, j])
        meas_q, meas_v = seg.q[ok, j], seg.qdot[ok, j]
        res_q.append(r.q[ok, j] - meas_q)
        tot_q.append(meas_q - meas_q.mean())
        res_v.append(r.qdot[ok, j] - meas_v)
        tot_v.append(meas_v - meas_v.mean())
    rq, tq = np.concatenate(res_q), np.concatenate(tot_q)
    rv, tv = np.concatenate(res_v), np.concatenate(tot_v)
    return Quality(
        r2=float(1.0 - rq @ rq / max(tq @ tq, 1e-30)),
        rms_rad=float(np.sqrt(np.mean(rq**2))),
        r2_velocity=float(1.0 - rv @ rv / max(tv @ tv, 1e-30)),
        rms_velocity=float(np.sqrt(np.mean(rv**2))),
        samples=int(rq.size),
    )
