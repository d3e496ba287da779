"""System identification of the Alpha 5 twin by simulation (docs/identification.md).

The data are current-mode motions of one joint at a time (`Segment`: the states a control loop
saw on its tick grid and the currents it held over each period, as `reach_driver`'s
`LoopTrace` gives them). The twin is `Alpha5Arm`, the model the controllers use. A
parameter set is scored by replaying the logged commands open loop through MuJoCo:

- multiple shooting: each segment is cut into windows of `window_s`; each window starts
  from the measured state (the excited joint's corrected by fitted nuisances,
  `Segment.start_fix`, where the fit has them), so a rollout cannot drift further than one
  window;
- the joints not being excited are held on their measured path (their position and
  velocity are set to the logged values at every tick), so one joint's fit does not
  depend on the others' parameters beyond what the pose makes them load it with;
- the link's transport delay: command row i (sent at tick i-1) lands at t[i-1] plus its
  delay, measured per command from the driver's timestamps (`link_delays`, the segment's
  `link_delay_s`) plus a constant per segment (`offset_s`, `tune_offsets`), on the arm's
  own step grid (`Replay.quantum_s`), and is held until the next lands;
- windows are cut where the link stalled (`Replay.windows`).

`fit_arm` fits each joint by Levenberg-Marquardt with forward-difference Jacobians over
log-parameters (armature, viscous damping, Coulomb friction of the joint, and a link mass for
the net gravity-buoyancy load where there is one) with the delays held fixed: fitted beside
the armature, one constant delay traded off against it (both delay the response to a current
step by a fraction of a tick). Each value gets an uncertainty from the Jacobian at the
optimum, sqrt(diag(sigma^2 (J^T J)^-1)). `fit_joint` can still fit a constant delay
(`DELAY`) where there are no timestamps. Numpy only.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocol.alpha5 import JOINT_LETTERS, N_JOINTS
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams

FloatArray = NDArray[np.float64]

DELAY = "delay_s"
"""The name of the transport-delay parameter (not an `ArmParams` field)."""

MAX_DELAY_S = 0.1
DEFAULT_WINDOW_S = 1.0
VELOCITY_WEIGHT_S = 0.02
"""Velocity residuals (rad/s) are weighted by this (s) next to position residuals (rad)."""
ROBUST_CLIP = 3.0
"""`Replay.window_weights`: windows worse than this times the median window are down-weighted."""
STALL_S = 0.02
"""A command measured later than this after its tick (s) cuts the replay's window there."""
PLAN_CACHE = 256  # command schedules kept by `Replay` (per segment and delay)
SKIP_TICKS = 3
"""Ticks at the start of a segment not used: the joints leave position mode there."""

#: Per tick, runs of (current held, physics steps): how `Replay` drives the arm.
Schedule = list[list[tuple[FloatArray, int]]]
#: A parameter: (ArmParams field, joint index) or (DELAY, -1).
ParamRef = tuple[str, int]


@dataclass(frozen=True)
class Segment:
    """One logged excitation: the loop's tick grid, one row per tick.

    ``command_mA[i]`` is the current the host held over the period ending at sample i (row 0
    is before the first command), as `reach_driver.records.LoopTrace.command_mA`."""

    name: str
    joint: int  # index in E D C B of the joint being excited
    role: str  # "fit" or "validate"
    period: float  # s between ticks
    q: FloatArray  # (n + 1, 4) rad
    qdot: FloatArray  # (n + 1, 4) rad/s
    command_mA: FloatArray  # (n + 1, 4)
    current_mA: FloatArray | None = None  # measured, NaN where not reported
    meta: dict[str, Any] = field(default_factory=dict)
    # Measured part of the transport delay of each command row (arm s; row 0 unused), from
    # the driver's timestamps (`link_delays`); NaN: no command was sent at that tick (the
    # loop was late and skipped it), the row holds the previous one; None: the delay is one
    # constant.
    link_delay_s: FloatArray | None = None
    # The constant added to this segment's delays (s), found by `tune_offsets`: the part of
    # the delay the timestamps cannot see (the least transit, the arm's own step).
    offset_s: float = 0.0
    # The excited joint's angle (rad) and speed (rad/s) at the start of each replay window,
    # added to the readings there: nuisances fitted beside the arm (`fit_joint`'s
    # `fit_starts`), one row per window of the replay that fitted them; None: each window
    # starts from the readings as they are.
    start_fix: FloatArray | None = None

    def __post_init__(self) -> None:
        for name in ("q", "qdot", "command_mA"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.ndim != 2 or arr.shape[1] != N_JOINTS or arr.shape[0] < 2:
                raise ValueError(f"segment {self.name}: {name} must be (n+1, 4), got {arr.shape}")
            object.__setattr__(self, name, arr)
        if not self.q.shape == self.qdot.shape == self.command_mA.shape:
            raise ValueError(f"segment {self.name}: q, qdot and command_mA differ in length")
        if not 0 <= self.joint < N_JOINTS:
            raise ValueError(f"segment {self.name}: joint index {self.joint} not in 0..3")
        if self.role not in ("fit", "validate"):
            raise ValueError(f"segment {self.name}: role must be fit or validate")
        if self.link_delay_s is not None:
            d = np.asarray(self.link_delay_s, dtype=float)
            if d.shape != (self.q.shape[0],) or not np.any(np.isfinite(d[1:])):
                raise ValueError(
                    f"segment {self.name}: link_delay_s must be ({self.q.shape[0]},) with a "
                    "finite delay for at least one command"
                )
            object.__setattr__(self, "link_delay_s", d)
        if self.start_fix is not None:
            fix = np.asarray(self.start_fix, dtype=float)
            if fix.ndim != 2 or fix.shape[1] != 2:
                raise ValueError(f"segment {self.name}: start_fix must be (windows, 2)")
            object.__setattr__(self, "start_fix", fix)

    @property
    def ticks(self) -> int:
        return int(self.q.shape[0] - 1)

    @property
    def seconds(self) -> float:
        return self.ticks * self.period


@dataclass(frozen=True)
class LinkTiming:
    """What the driver's timestamps say about one run's link (`link_delays`)."""

    delays_s: FloatArray  # (n + 1,) arm s from tick i-1 to command row i landing; row 0 NaN
    arm_speed: float  # arm seconds per host second (the lower envelope's slope)
    p50_s: float
    p99_s: float


DELAY_ENVELOPE_S = 0.5
"""Half-width (arm s) of the running minimum that tracks the clock offset (`link_delays`)."""


def _lower_hull_line(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    """(intercept, slope) of the line under every point (x, y) that is closest to them on
    average: the lower convex hull's edge above mean(x) (a two-variable linear program)."""
    hull: list[int] = []
    for i in np.argsort(x, kind="stable"):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            cross = (x[b] - x[a]) * (y[i] - y[a]) - (y[b] - y[a]) * (x[i] - x[a])
            if cross <= 0:
                hull.pop()
            else:
                break
        hull.append(int(i))
    if len(hull) < 2:
        return float(y[hull[0]]), 0.0
    xm = float(np.mean(x))
    for a, b in zip(hull[:-1], hull[1:], strict=True):
        if x[b] >= xm or b == hull[-1]:
            slope = float((y[b] - y[a]) / (x[b] - x[a]))
            return float(y[a] - slope * x[a]), slope
    raise AssertionError("unreachable")


def link_delays(
    t: FloatArray,
    received: FloatArray,
    written: FloatArray,
    envelope_s: float = DELAY_ENVELOPE_S,
) -> LinkTiming:
    """The measured part of each command's transport delay, in arm time, from what the host
    knows: tick k's arm time ``t[k]`` (the heartbeat count), the host time its state was
    complete ``received[k]`` and the host time the command made from it was written
    ``written[k]`` (k = 0 .. n-1; the command is row k + 1 of the segment).

    Why: a fitted constant delay trades off against the armature (both delay the response to a
    current step by a fraction of a tick), and on a loaded host the real delay is not one
    number. The arm's clock is mapped to the host's by the lower envelope of ``received -
    t / speed`` (the least transit seen): its slope gives the arm speed (1 on a real arm,
    `reach-sim --speed` on a virtual one), a running minimum over +-`envelope_s` follows
    offset steps (a simulator that fell behind re-anchors its clock; the minimum looks ahead
    over 2 `envelope_s`). A command written at
    host time w then lands at arm time ``(w - offset) * speed`` plus the least transit and
    whatever the arm itself adds, which is the same for every command: that constant is left
    to the fit. Returns per command row the delay after its tick (row 0 NaN)."""
    t = np.asarray(t, dtype=float)
    received = np.asarray(received, dtype=float)
    written = np.asarray(written, dtype=float)
    if not t.shape == received.shape == written.shape or t.ndim != 1 or t.size < 2:
        raise ValueError("link_delays needs three equal 1-D arrays of at least 2 ticks")
    if not (np.all(np.isfinite(received)) and np.all(np.isfinite(written))):
        raise ValueError("link_delays: timestamps must be finite")
    # received = offset + t / speed + transit: the envelope's slope is 1 / speed.
    _, inv_speed = _lower_hull_line(t, received)
    if not inv_speed > 0:
        raise ValueError("link_delays: the arm's clock does not advance against the host's")
    speed = 1.0 / inv_speed
    offset = received - t * inv_speed
    period = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    half = max(int(round(envelope_s / max(period, 1e-9))), 1)
    # The minimum over the ticks ahead (the last ones share the final window): the offset
    # only ever steps up (a simulator re-anchors later, never earlier), so looking ahead
    # never reaches across a step to the lower offset before it.
    span = min(2 * half + 1, offset.size)
    ahead = np.lib.stride_tricks.sliding_window_view(offset, span).min(axis=1)
    floor = np.concatenate([ahead, np.full(offset.size - ahead.size, ahead[-1])])
    delay = np.maximum((written - floor) * speed - t, 0.0)
    out = np.concatenate([[np.nan], delay])
    return LinkTiming(
        delays_s=out,
        arm_speed=speed,
        p50_s=float(np.percentile(delay, 50)),
        p99_s=float(np.percentile(delay, 99)),
    )


@dataclass(frozen=True)
class Rollout:
    """The twin's prediction of a segment: NaN where no prediction (window starts)."""

    q: FloatArray
    qdot: FloatArray
    window: NDArray[np.int64] | None = None  # per row: the window that predicted it, or -1


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

    def simulate(
        self, params: ArmParams, delay_s: float, seg: Segment, window_s: float | None = None
    ) -> Rollout:
        """The twin `params` driven by the segment's commands (see the module docstring).
        ``window_s`` <= 0 or inf: one window from the first usable tick to the end."""
        arm = self.arm
        arm.set_params(params)
        self.rollouts += 1
        w_ticks = self.window_ticks(seg, window_s)
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
        plan = cached[2]
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
            j = seg.joint
            ok = np.isfinite(r.q[:, j])
            parts.append(r.q[ok, j] - seg.q[ok, j])
            if velocity_weight > 0:
                parts.append(velocity_weight * (r.qdot[ok, j] - seg.qdot[ok, j]))
            if seg.start_fix is not None:
                parts.append(seg.start_fix[:, 0])
                parts.append(velocity_weight * seg.start_fix[:, 1])
        return np.concatenate(parts) if parts else np.zeros(0)

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


@dataclass(frozen=True)
class FitResult:
    """One joint's fit: values, 1-sigma uncertainties, and the cost history."""

    joint: int
    refs: tuple[ParamRef, ...]
    values: tuple[float, ...]
    sigma: tuple[float, ...]
    params: ArmParams
    delay_s: float
    rms_residual: float
    iterations: int
    rollouts: int
    costs: tuple[float, ...]
    segments: tuple[Segment, ...] = ()  # as fitted: with their window starts when fitted

    def table(self) -> dict[str, dict[str, float]]:
        return {
            ref_name(r): {"value": v, "sigma": s}
            for r, v, s in zip(self.refs, self.values, self.sigma, strict=True)
        }


def default_refs(joint: int, fit_delay: bool = True) -> list[ParamRef]:
    """What a current-controlled joint reveals (docs/identification.md): its armature,
    viscous and Coulomb friction, the net gravity-buoyancy load where there is one (D: the
    link D moves, C: the wrist link, which is most of C's load), and the link's delay."""
    refs: list[ParamRef] = [("armature", joint), ("damping", joint), ("frictionloss", joint)]
    letter = JOINT_LETTERS[joint]
    if letter == "D":
        refs.append(("link_mass_kg", joint))
    elif letter == "C":
        refs.append(("link_mass_kg", JOINT_LETTERS.index("B")))
    if fit_delay:
        refs.append((DELAY, -1))
    return refs


FRICTION_FLOOR = 1e-4  # N m: log-parameters need a positive start
MAX_LOG_STEP = 1.0
"""`fit_joint` moves no log-parameter by more than this per step (a factor of e): a full
Gauss-Newton step from a start far off (the nominal 0.7 N m of friction on a frictionless
joint, under 3x sensor noise) once threw a joint's damping to the floor, where its gradient
vanishes and the fit cannot come back (docs/identification.md, "Arms of the envelope")."""


MOVED_RAD = 0.05
"""`friction_ceiling`: a joint whose angle spanned this much in its segments was seen moving."""


def friction_ceiling(replay: Replay, params: ArmParams, segments: Sequence[Segment]) -> float:
    """The most Coulomb friction (N m) the segments allow their joint: seen moving, it was
    driven past its friction, so the friction is under the largest torque that could have
    done it (the drive's at the largest current held, at `params`' torque scale, plus the
    gravity-buoyancy load at the poses held). inf for a joint not seen moving. Why: MuJoCo's
    friction constraint is soft, and friction the drive can never break acts as damping; a
    weak B at 3x noise was fitted as 2.25 N m of friction (its drive gave at most 0.86) beside
    a sixth of its armature, and a controller fed that friction forward chattered."""
    j = segments[0].joint
    if max(float(np.ptp(s.q[:, j])) for s in segments) < MOVED_RAD:
        return math.inf
    arm = replay.arm
    arm.set_params(params)
    peak_mA = max(float(np.max(np.abs(s.command_mA[:, j]))) for s in segments)
    drive = params.torque_scale[j] * float(arm.motor.torque_per_amp[j]) * peak_mA / 1000.0
    load = max(
        abs(float(arm.gravity_torque(q)[j]))
        for s in segments
        for q in s.q[:: max(1, len(s.q) // 50)]
    )
    return drive + load


START_STEP = (1e-3, 1e-2)
"""`fit_joint`'s difference steps in a window's start angle (rad) and speed (rad/s)."""


def fit_joint(
    replay: Replay,
    segments: Sequence[Segment],
    start: ArmParams,
    delay_s: float,
    refs: Sequence[ParamRef],
    max_iter: int = 12,
    tol: float = 1e-4,
    velocity_weight: float = VELOCITY_WEIGHT_S,
    on_iteration: Callable[[int, float], None] | None = None,
    weights: FloatArray | None = None,
    fit_starts: bool = False,
) -> FitResult:
    """Levenberg-Marquardt over `refs` (log of each physical value; the delay in seconds)
    on the residuals of `segments`, starting from `start` and `delay_s`.

    With `fit_starts`, each window's starting angle and speed of the excited joint are fitted
    too (`Segment.start_fix`, from the segments' own or zero). Why: a window started from a
    noisy reading carries the reading's error, and a lighter twin forgets it sooner; at 3x
    sensor noise that biased D's and C's armature 13-19 % low (docs/identification.md). The
    starts are separable (each moves its own window only), so their Jacobian costs two
    rollouts whatever their number. Off by default: beside an arm still far from the data
    the starts soak up its errors, so `fit_arm` fits them only in its polish."""
    refs = tuple(refs)
    if not segments:
        raise ValueError("no segments to fit")
    joint = segments[0].joint
    segs = replay.with_starts(segments) if fit_starts else list(segments)
    counts = [0 if s.start_fix is None else s.start_fix.shape[0] for s in segs]
    n_fix = sum(counts) if fit_starts else 0
    n_par = len(refs)
    is_log = np.concatenate([[r[0] != DELAY for r in refs], np.zeros(2 * n_fix, dtype=bool)])
    x0 = np.array(
        [
            math.log(max(param_value(start, delay_s, r), FRICTION_FLOOR))
            if r[0] != DELAY
            else param_value(start, delay_s, r)
            for r in refs
        ]
    )
    if n_fix:
        fixes = [s.start_fix for s in segs if s.start_fix is not None]
        x0 = np.concatenate([x0, *[f[:, 0] for f in fixes], *[f[:, 1] for f in fixes]])
    lower = np.concatenate(
        [np.where(is_log[:n_par], math.log(FRICTION_FLOOR), 0.0), np.full(2 * n_fix, -np.inf)]
    )
    ceiling = friction_ceiling(replay, start, segs)

    def top(ref: ParamRef) -> float:
        if ref[0] == DELAY:
            return MAX_DELAY_S
        if ref[0] == "torque_scale":
            return 0.0  # a drive delivers at most its full torque
        if ref == ("frictionloss", joint) and math.isfinite(ceiling):
            return math.log(max(ceiling, 10 * FRICTION_FLOOR))
        return math.log(1e3)

    upper = np.concatenate([[top(r) for r in refs], np.full(2 * n_fix, np.inf)])
    step = np.where(is_log[:n_par], 0.01, 0.0005)
    rollouts0 = replay.rollouts
    row_window = replay.residual_windows(segs, velocity_weight) if n_fix else None

    def unpack(x: FloatArray) -> tuple[ArmParams, float]:
        physical = np.where(is_log[:n_par], np.exp(x[:n_par]), x[:n_par])
        delay = delay_s
        for r, v in zip(refs, physical, strict=True):
            if r[0] == DELAY:
                delay = float(v)
        return params_with(start, refs, physical.tolist()), delay

    def starts_at(x: FloatArray) -> list[Segment]:
        if not n_fix:
            return segs
        out, i = [], n_par
        for s, c in zip(segs, counts, strict=True):
            fix = np.column_stack([x[i : i + c], x[n_fix + i : n_fix + i + c]])
            out.append(replace(s, start_fix=fix))
            i += c
        return out

    def fun(x: FloatArray) -> FloatArray:
        p, d = unpack(x)
        r = replay.residuals(p, d, starts_at(x), velocity_weight)
        return r if weights is None else r * weights

    def jacobian(x: FloatArray, r0: FloatArray) -> FloatArray:
        cols = []
        for i in range(n_par):
            h = step[i] if x[i] + step[i] <= upper[i] else -step[i]
            xp = x.copy()
            xp[i] += h
            cols.append((fun(xp) - r0) / h)
        jac = np.column_stack(cols)
        if not n_fix or row_window is None:
            return jac
        # every window's start at once: window w's rows answer its own start only
        starts = np.zeros((r0.size, 2 * n_fix))
        for block, h in enumerate(START_STEP):
            xp = x.copy()
            xp[n_par + block * n_fix : n_par + (block + 1) * n_fix] += h
            starts[np.arange(r0.size), block * n_fix + row_window] = (fun(xp) - r0) / h
        return np.hstack([jac, starts])

    x = np.clip(x0, lower, upper)
    r = fun(x)
    if row_window is not None and row_window.size != r.size:
        raise RuntimeError(f"{r.size} residuals for {row_window.size} window rows")
    cost = float(r @ r)
    costs = [cost]
    lam = 1e-3
    it = 0
    jac = jacobian(x, r)
    for it in range(1, max_iter + 1):
        g = jac.T @ r
        h = jac.T @ jac
        diag = np.maximum(np.diag(h), 1e-12)
        improved = False
        for _ in range(8):
            try:
                dx = np.linalg.solve(h + lam * np.diag(diag), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            # each on its own: scaling the whole step would let a parameter the data barely
            # see (friction near zero) shrink the step of the ones they do
            dx = np.where(is_log, np.clip(dx, -MAX_LOG_STEP, MAX_LOG_STEP), dx)
            x_new = np.clip(x + dx, lower, upper)
            r_new = fun(x_new)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                improved = True
                gain = (cost - cost_new) / max(cost, 1e-30)
                x, r, cost = x_new, r_new, cost_new
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 4.0
        costs.append(cost)
        if on_iteration is not None:
            on_iteration(it, cost)
        if not improved or gain < tol:
            break
        jac = jacobian(x, r)
    # Uncertainty at the optimum (the last Jacobian is at x unless the step was refused).
    jac = jacobian(x, r)
    dof = max(r.size - x.size, 1)
    sigma2 = cost / dof
    try:
        cov = sigma2 * np.linalg.inv(jac.T @ jac)
        std_x = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        std_x = np.full(x.size, np.inf)
    physical = np.where(is_log, np.exp(x), x)[:n_par]
    std = np.where(is_log, np.exp(x) * std_x, std_x)[:n_par]
    params, delay = unpack(x)
    return FitResult(
        joint=joint,
        refs=refs,
        values=tuple(float(v) for v in physical),
        sigma=tuple(float(s) for s in std),
        params=params,
        delay_s=delay,
        rms_residual=math.sqrt(cost / max(r.size, 1)),
        iterations=it,
        rollouts=replay.rollouts - rollouts0,
        costs=tuple(costs),
        segments=tuple(starts_at(x)),
    )


#: `coarse_start`'s grid, as multiples of the nominal arm's value of each parameter. Coulomb
#: friction spans the envelope's 0 - 6.6 N m for E D C (the model's 0.7 x 0 ... 10: the
#: sources disagree tenfold), the rest its +-50 % (armature, damping) and the net load's
#: +-20 % of mass and buoyancy (an effective link mass 0.7 - 1.3 x nominal for D).
COARSE_GRID: dict[str, tuple[float, ...]] = {
    "armature": (0.5, 1.0, 2.0),
    "damping": (0.5, 1.0, 2.0),
    "frictionloss": (0.0, 0.15, 1.0, 3.0, 10.0),
    "link_mass_kg": (0.7, 1.0, 1.3),
}
DRIVE_SCALES: tuple[float, ...] = (1.0, 0.25)
"""`coarse_start` tries the grid at each of these torque scales of the joint's drive (the
envelope's weak joint runs at 25 %): a weak D, whose drive fights its own load, was fitted
from full torque as 12.6 N m of Coulomb friction (validation R^2 0.71). The scale found is
kept through the fit (beside the load it is a trade the data hardly see) unless the fit has
it among its own parameters (a weak C's refit)."""
DRIVE_MARGIN = 0.5
"""... and a weaker drive than the first must fit with at most this share of its squared
residual: for a joint without a load a weak drive and a heavier joint move alike, and a
healthy E once came out at a quarter torque by a 0.80 ratio (weak joints measured 0.10-0.45,
a weak B 0.76)."""


def coarse_start(
    replay: Replay,
    segments: Sequence[Segment],
    base: ArmParams,
    refs: Sequence[ParamRef],
    velocity_weight: float = VELOCITY_WEIGHT_S,
) -> ArmParams:
    """`base`, or `base` with `refs` (and the joint's torque scale, `DRIVE_SCALES`) set to the
    best point of `COARSE_GRID` (around the nominal arm's values) if one fits the segments
    better: where Levenberg-Marquardt starts.
    From the nominal arm alone a frictionless joint under 3x sensor noise was fitted at 7x
    its damping (and once at 20x its armature): the residual far from the arm is no guide."""
    nominal = ArmParams()
    joint = segments[0].joint
    axes: list[list[tuple[ParamRef, float]]] = []
    if ("torque_scale", joint) not in refs:
        axes.append([(("torque_scale", joint), s) for s in DRIVE_SCALES])
    for name, j in refs:
        if name not in COARSE_GRID:  # the delay, a torque scale: kept as in `base`
            continue
        ref_value = getattr(nominal, name)[j]
        axes.append([((name, j), max(f * ref_value, FRICTION_FLOOR)) for f in COARSE_GRID[name]])

    def cost(p: ArmParams) -> float:
        res = replay.residuals(p, 0.0, segments, velocity_weight)
        return float(res @ res)

    by_scale: dict[float, tuple[float, ArmParams]] = {}
    for point in itertools.product(*axes):
        trial = params_with(base, [ref for ref, _ in point], [v for _, v in point])
        c, scale = cost(trial), trial.torque_scale[joint]
        if scale not in by_scale or c < by_scale[scale][0]:
            by_scale[scale] = (c, trial)
    best_cost, best = cost(base), base  # unless a grid point does better
    for scale in sorted(by_scale, reverse=True):  # the strongest drive first
        c, trial = by_scale[scale]
        margin = DRIVE_MARGIN if scale < best.torque_scale[joint] else 1.0
        if c < margin * best_cost:
            best_cost, best = c, trial
    return best


WRIST_LOAD: ParamRef = ("link_mass_kg", JOINT_LETTERS.index("B"))
"""The wrist link's mass: most of C's load, and part of D's."""
WEAK_RATIO = 0.8
"""`fit_arm` takes C for a weak drive (its torque scale the ratio) when D carries the wrist at
less than this share of the weight C's fit gave it (the envelope's heaviest and lightest
wrists differ by 2.6x in net weight, a drive at 25 % torque by 4x)."""


def wrist_weight(params: ArmParams, mass: float | None = None) -> float:
    """The wrist link's net weight in water (kg), with `mass` in place of its own."""
    b = WRIST_LOAD[1]
    m = params.link_mass_kg[b] if mass is None else mass
    return m - params.link_volume_l[b] * 1e-3 * params.water_density


JOINT_ORDER = ("E", "B", "C", "D")
"""Fitting order: E and B carry no gravity load; C's load (the wrist link) is fitted before
D, whose load includes it."""


OFFSET_SPAN_S = 0.01
"""`tune_offsets` searches +-this (s) around zero when the timestamps measured the delays ..."""
OFFSET_STEP_S = 0.001
"""... on this grid, then refines twice by half a step (to 0.25 ms)."""
CONSTANT_DELAY_MAX_S = 0.03
"""... and 0 .. this when they did not (the whole delay is then one constant)."""
QUANTA_S = (0.002, 0.0)
"""The arm's command steps `fit_arm` chooses between: the virtual arm steps its physics (and
takes commands) every 2 ms; a real arm's current loop is fast enough to count as 0."""


def tune_offsets(
    replay: Replay,
    params: ArmParams,
    segments: Sequence[Segment],
    velocity_weight: float = VELOCITY_WEIGHT_S,
) -> list[Segment]:
    """Each segment with the delay offset (a nuisance, one per segment) that fits it best on
    `params`, by a grid search then two half-step refinements: with commands taken on the arm's
    step grid the residual is piecewise constant in the offset (no gradient to follow), and
    the offset left by the timestamps' clock mapping differs from run to run by a fraction of
    a millisecond (the least transit seen in that run)."""
    out = []
    for seg in segments:
        if seg.link_delay_s is not None:
            grid = np.arange(-OFFSET_SPAN_S, OFFSET_SPAN_S + 1e-12, OFFSET_STEP_S)
        else:
            grid = np.arange(0.0, CONSTANT_DELAY_MAX_S + 1e-12, OFFSET_STEP_S)

        def cost(offset: float, seg: Segment = seg) -> float:
            r = replay.residuals(
                params, 0.0, [replace(seg, offset_s=float(offset))], velocity_weight
            )
            return float(r @ r)

        costs = [cost(o) for o in grid]
        best_cost, best = min(zip(costs, grid.tolist(), strict=True))
        step = float(grid[1] - grid[0]) if grid.size > 1 else OFFSET_STEP_S
        for _ in range(2):  # refine: half a step either side, twice
            step /= 2
            for o in (best - step, best + step):
                c = cost(o)
                if c < best_cost:
                    best_cost, best = c, o
        candidates = [(best_cost, best)]
        out.append(replace(seg, offset_s=min(candidates)[1]))
    return out


def segment_delays(seg: Segment, extra_s: float = 0.0) -> FloatArray:
    """The delay of each command row the replay uses (s; rows 1..n)."""
    d = np.full(seg.ticks, seg.offset_s + extra_s)
    if seg.link_delay_s is not None:
        d += seg.link_delay_s[1:]
    d = d[np.isfinite(d)]
    return np.clip(d, 0.0, MAX_DELAY_S)


@dataclass(frozen=True)
class ArmFit:
    """`fit_arm`'s result: the arm, each joint's fit, the segments with their delay offsets,
    the command step chosen, and the median delay the replay used."""

    params: ArmParams
    results: dict[int, FitResult]
    segments: tuple[Segment, ...]  # the fitting segments, offsets tuned on the fitted arm
    quantum_s: float
    delay_s: float  # median over every command of every fitting segment


def fit_arm(
    replay: Replay,
    segments: Sequence[Segment],
    start: ArmParams | None = None,
    max_iter: int = 12,
    on_joint: Callable[[int, FitResult], None] | None = None,
    on_iteration: Callable[[int, int, float], None] | None = None,
    quanta: Sequence[float] = QUANTA_S,
    fit_starts: bool = True,
) -> ArmFit:
    """Fit every joint that has "fit" segments, in `JOINT_ORDER`, each from the arm found so
    far, with the delay held out of the physical fit (it trades off against the armature):

    1. Levenberg-Marquardt over the joint's physical parameters with the delays fixed at what
       the driver's timestamps measured per command (`link_delays`; offsets zero);
    2. each segment's delay offset is tuned on the fitted joint (`tune_offsets`) and the fit
       polished from there.

    With `fit_starts` the polish fits each window's starting state too (`fit_joint`).

    On the first joint the arm's command step is chosen among `quanta` (the one whose
    re-tuned median window error is smallest; a fresh fit if it is not the first tried)."""
    params = start if start is not None else ArmParams()
    results: dict[int, FitResult] = {}
    by_joint: dict[int, list[Segment]] = {}
    wrist_c: float | None = None  # the wrist link's mass as C's fit saw it
    quanta = tuple(quanta) or (replay.quantum_s,)
    replay.quantum_s = float(quanta[0])
    first = True
    for letter in JOINT_ORDER:
        j = JOINT_LETTERS.index(letter)
        segs = [s for s in segments if s.joint == j and s.role == "fit"]
        if not segs:
            continue

        def note(it: int, cost: float, j: int = j) -> None:
            if on_iteration is not None:
                on_iteration(j, it, cost)

        def one(
            base: ArmParams,
            segs: list[Segment] = segs,
            j: int = j,
            refs: list[ParamRef] | None = None,
            coarse: bool = True,
        ) -> tuple[FitResult, list[Segment]]:
            refs = refs or default_refs(j, fit_delay=False)
            # Offsets start at zero (the timestamps' word): tuned on an arm still far from
            # this one they would soak up its errors, the very trade-off they are to avoid.
            ready = [replace(x, offset_s=0.0) for x in segs]
            if coarse:
                base = coarse_start(replay, ready, base, refs)
            result = fit_joint(
                replay,
                ready,
                base,
                0.0,
                refs,
                max_iter=max_iter,
                on_iteration=note,
                # window starts only in the polish: fitted beside an arm still far from this
                # one they soak up its errors as the offsets would (and mislead the offsets)
                fit_starts=False,
            )
            ready = tune_offsets(replay, result.params, ready)
            if fit_starts:
                ready = replay.with_starts(ready)
            weights = replay.window_weights(result.params, 0.0, ready)
            polished = fit_joint(
                replay,
                ready,
                result.params,
                0.0,
                refs,
                max_iter=max(3, max_iter // 2),
                on_iteration=note,
                weights=weights,
                fit_starts=fit_starts,
            )
            return replace(
                polished,
                iterations=result.iterations + polished.iterations,
                rollouts=result.rollouts + polished.rollouts,
                costs=result.costs + polished.costs,
            ), list(polished.segments)

        refs_j = default_refs(j, fit_delay=False)
        if letter == "D" and wrist_c is not None:
            refs_j.append(WRIST_LOAD)  # the wrist's weight as D carries it
        result, ready = one(params, refs=refs_j)
        if first and len(quanta) > 1:

            def plain_cost(p: ArmParams, segs: list[Segment]) -> float:
                # The median window, not the sum: on a loaded host a few stalled windows
                # replay badly under either step and would decide the choice.
                return replay.median_window_rms(p, 0.0, segs)

            best = (plain_cost(result.params, ready), replay.quantum_s, result, ready)
            for q in quanta[1:]:
                replay.quantum_s = float(q)
                trial = tune_offsets(replay, result.params, ready)
                if plain_cost(result.params, trial) < best[0]:
                    res_q, ready_q = one(params, refs=refs_j)
                    cost_q = plain_cost(res_q.params, ready_q)
                    if cost_q < best[0]:
                        best = (cost_q, float(q), res_q, ready_q)
            _, quantum, result, ready = best
            replay.quantum_s = quantum
        first = False
        params = result.params
        results[j] = result
        by_joint[j] = ready
        if letter == "C":
            wrist_c = params.link_mass_kg[WRIST_LOAD[1]]
        if letter == "D" and wrist_c is not None:
            # C's drive and the wrist's weight are one unknown to C's fit; D carries the
            # wrist without C's drive. A C that saw the wrist heavier than D does is weak.
            scale = wrist_weight(params) / max(wrist_weight(params, wrist_c), 1e-9)
            c = JOINT_LETTERS.index("C")
            if 0.0 < scale < WEAK_RATIO:
                refs_c = [*default_refs(c, fit_delay=False)[:3], ("torque_scale", c)]
                scaled = [v * scale for v in results[c].values[:3]]
                refit, ready_c = one(
                    params_with(params, refs_c, [*scaled, scale]),
                    [x for x in segments if x.joint == c and x.role == "fit"],
                    c,
                    refs_c,
                )
                params, results[c], by_joint[c] = refit.params, refit, ready_c
            else:  # C keeps the wrist it saw; D is fitted again with it
                held = params_with(params, [WRIST_LOAD], [wrist_c])
                result, ready = one(held, coarse=False)
                params, results[j], by_joint[j] = result.params, result, ready
        if on_joint is not None:
            on_joint(j, result)
    tuned = [x for j in sorted(by_joint) for x in by_joint[j]]
    delays = np.concatenate([segment_delays(s) for s in tuned]) if tuned else np.zeros(1)
    return ArmFit(params, results, tuple(tuned), replay.quantum_s, float(np.median(delays)))


def segment_from_index(
    meta: dict[str, Any],
    q: FloatArray,
    qdot: FloatArray,
    command_mA: FloatArray,
    current_mA: FloatArray | None,
    link_delay_s: FloatArray | None,
) -> Segment:
    """A segment from its index entry (name, joint, role, period, meta: as `save_segments`
    and tools/identify.py's recording write it) and its arrays."""
    return Segment(
        name=meta["name"],
        joint=int(meta["joint"]),
        role=meta["role"],
        period=float(meta["period"]),
        q=q,
        qdot=qdot,
        command_mA=command_mA,
        current_mA=current_mA,
        meta=dict(meta.get("meta", {})),
        link_delay_s=link_delay_s,
    )


def load_segments(path: Any) -> list[Segment]:
    """Segments from an `.npz` log written by `save_segments` (tools/identify.py)."""
    import json

    with np.load(path, allow_pickle=False) as data:
        index = json.loads(str(data["index"]))
        out = []
        for i, meta in enumerate(index):
            cur = data[f"s{i}_current_mA"] if f"s{i}_current_mA" in data else None
            link = data[f"s{i}_link_delay_s"] if f"s{i}_link_delay_s" in data else None
            out.append(
                segment_from_index(
                    meta, data[f"s{i}_q"], data[f"s{i}_qdot"], data[f"s{i}_command_mA"], cur, link
                )
            )
    return out


def save_segments(segments: Sequence[Segment], path: Any, header: dict[str, Any]) -> None:
    """One `.npz`: per segment q, qdot, command_mA, current_mA, and a JSON index (name,
    joint, role, period, meta) plus `header` (how the log was made)."""
    import json

    arrays: dict[str, Any] = {}
    index = []
    for i, seg in enumerate(segments):
        arrays[f"s{i}_q"] = seg.q
        arrays[f"s{i}_qdot"] = seg.qdot
        arrays[f"s{i}_command_mA"] = seg.command_mA
        if seg.current_mA is not None:
            arrays[f"s{i}_current_mA"] = np.asarray(seg.current_mA, dtype=float)
        if seg.link_delay_s is not None:
            arrays[f"s{i}_link_delay_s"] = seg.link_delay_s
        index.append(
            {
                "name": seg.name,
                "joint": seg.joint,
                "role": seg.role,
                "period": seg.period,
                "meta": seg.meta,
            }
        )
    np.savez_compressed(
        path, index=np.array(json.dumps(index)), header=np.array(json.dumps(header)), **arrays
    )
