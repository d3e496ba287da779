"""A per-joint settle supervisor around the distilled actor: engineered, not learned.

Why: the actor is stateless, with one near-goal gain for every arm. With 1-2 periods of control
latency and little Coulomb friction that gain drives a joint into a limit cycle about its goal;
on a light joint (B) or under 2-3x sensor noise it jitters there; a weak or high-friction joint
stops short of it. The supervisor hands *that joint* to a conservative settle law and leaves the
approach, and every joint that settles normally, to the actor (on Table I's standard episodes
it never engages). It ships in `ddpg-distilled`; `ddpg-distilled --param settle=0` turns it off
and `ddpg-distilled-pure` has none (docs/robustness.md, "The settle supervisor"). Its numbers,
each with what set it, are `policy.controllers.settle_law.SettleLaw`'s fields.

What it watches, per joint: the error to the goal and the speed, low-passed (`filter_s`); the
sensors' noise, estimated from successive samples while the joint is slow, so that "moving"
and "broken away" mean `noise_sigmas` beyond it; and the loop's latency, timed once per loop
from how late the joints start after a target's first hard commands (`onset_*`).

When it engages (`Reason`), a joint near its goal:

- cycling: within `band`, the actor's command reverses `reversals` times, none over
  `max_gap_s` apart, over at least `min_span_s`;
- crossing: it crosses its goal at `crossing_speed`, or on a loop timed at `latent_periods`
  or more at `latent_crossing_speed`, also `latent_ahead` periods before it would;
- reversing: within `band` (`prompt_joints`), its measured speed reverses between two
  samples at `reversing_speed` or more both ways;
- jitter: `jitter_s` inside `jitter_band`, its speed's RMS over `jitter_window_s` exceeds
  `jitter_speed` (lower on a quiet arm: `jitter_true_speed`);
- hold (`hold_s` > 0): settled inside `hold_error` that long;
- stuck: within `stuck_band`, outside `stuck_error` and slow for `stuck_s`, not creeping in.

What it commands on an engaged joint: u = u_I + kp e - kd qdot (mA). u_I starts at the actor's
own hold on the goal (a stuck joint's at the actor's low-passed command, which held it there)
and integrates ki e outside `freeze`. A joint stuck outside `stuck_error` ramps towards its goal
to overcome friction: backed off at breakaway, restarted near where it last broke away,
slowed each time it hunts across the goal, the backoff given back if the breakaway proves to
be noise; a stuck joint creeping into its goal has `arrive` taken off its command. A joint
moved onto the actor's hold that then moves away with it, falls, or coasts on past its goal
(a weak or heavy joint) has that hold marked bad: it ramps back (`fall_ramp`) under
`fall_gain` times the gains.

When it releases: an engaged joint further than `release` from its goal is the actor's again,
and watched again. A new target starts every joint afresh (the latency, once timed, stays).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from policy.controllers.settle_law import SettleLaw
from protocol.alpha5 import JOINT_LETTERS, N_JOINTS

# Time constant of the noise estimates (s): 20 samples at 20 Hz, a spread known to +-20 %.
NOISE_FILTER_S = 1.0
# ... and the weight (of 1) an estimate has gathered from its start at 0 before it is trusted
NOISE_SETTLED = 0.8


class Reason(str, Enum):
    """Why a joint was handed to the settle law (`SettleSupervisor.reasons`; its value is the
    report's "reason")."""

    NONE = ""  # not engaged on this target
    CYCLING = "cycling"
    CROSSING = "crossing"
    CROSSING_AHEAD = "crossing ahead"
    REVERSING = "reversing"
    JITTER = "jitter"
    HOLD = "hold"
    STUCK = "stuck"

    def __str__(self) -> str:
        return self.value


def _per_joint(value: float | bool | int) -> Any:
    """A dataclass field holding one `value` per joint, of its type (float, bool or int)."""
    return field(default_factory=lambda: np.full(N_JOINTS, value, dtype=type(value)))


@dataclass
class _Filtered:
    """The low-passed signals (EMAs), started at a target's first sample."""

    e: np.ndarray = _per_joint(0.0)  # rad: the error to the goal (`filter_s`)
    v: np.ndarray = _per_joint(0.0)  # rad/s: the measured speed (`filter_s`)
    u: np.ndarray = _per_joint(0.0)  # mA: the actor's command (`hold_filter_s`)
    fresh: np.ndarray = _per_joint(True)  # no sample yet on this target


@dataclass
class _Noise:
    """The sensors' noise per joint, from successive samples while the joint is slow."""

    q_var: np.ndarray = _per_joint(0.0)  # rad^2: of the position
    v_var: np.ndarray = _per_joint(0.0)  # (rad/s)^2: of the speed
    v_w: np.ndarray = _per_joint(0.0)  # the weight the speed EMA has gathered (from 0)
    q_hist: np.ndarray = field(  # the errors of the two samples before, oldest first
        default_factory=lambda: np.full((2, N_JOINTS), math.nan)
    )
    v_prev: np.ndarray = _per_joint(math.nan)  # rad/s: the speed of the sample before


@dataclass
class _Watch:
    """The watches on a joint the actor holds."""

    v2: np.ndarray  # (window, joint): the last `jitter_window_s` of squared speeds, a ring
    v2_n: int = 0  # samples written into `v2`
    sign: np.ndarray = _per_joint(0.0)  # the sign of the last strong actor command (0: none)
    rev_start: np.ndarray = _per_joint(math.nan)  # s: the first reversal of this run
    rev_last: np.ndarray = _per_joint(math.nan)  # s: the last reversal
    rev_count: np.ndarray = _per_joint(0)  # reversals in this run
    stuck_for: np.ndarray = _per_joint(0.0)  # s the stuck watch has seen it stuck
    stuck_e0: np.ndarray = _per_joint(0.0)  # abs(e_f) when the stuck watch's timer began
    held_for: np.ndarray = _per_joint(0.0)  # s settled inside `hold_error`
    in_band_for: np.ndarray = _per_joint(0.0)  # s inside `jitter_band`
    e_prev: np.ndarray = _per_joint(0.0)  # rad: the error of the sample before (crossings)


@dataclass
class _Ramp:
    """The stuck ramp of an engaged joint and its breakaways."""

    ramped: np.ndarray = _per_joint(0.0)  # mA added since the joint stuck (what a backoff takes)
    was_stuck: np.ndarray = _per_joint(False)  # ramping, until it breaks away
    stuck_from: np.ndarray = _per_joint(0.0)  # rad: abs(e_f) where the ramp began
    side: np.ndarray = _per_joint(0.0)  # the side of the goal it last ramped from
    scale: np.ndarray = _per_joint(1.0)  # of `ramp`: shrinks by `ramp_decay` per side change
    rate: np.ndarray = _per_joint(1.0)  # 1, `memory_rate` restarted from memory, `creep_rate`
    since_break: np.ndarray = _per_joint(math.inf)  # s since the last breakaway
    break_u: np.ndarray = field(  # mA, per side (+, -): the command it last broke away at
        default_factory=lambda: np.full((N_JOINTS, 2), math.nan)
    )
    # a breakaway until `restick_s` later (`confirm_breakaway`): the ramp it ended (its
    # backoff was `backoff` of that) and the memory it replaced
    brk_pending: np.ndarray = _per_joint(False)
    brk_ramped: np.ndarray = _per_joint(0.0)
    brk_prev: np.ndarray = _per_joint(math.nan)


@dataclass
class _Arrival:
    """An engaged joint's arrivals and crossings of its goal (`arrive`, `creep_rate`)."""

    arriving: np.ndarray = _per_joint(False)  # armed outside 2 `stuck_error`, until inside
    side: np.ndarray = _per_joint(0.0)  # the side of the goal e_f was last on, outside `freeze`
    took: np.ndarray = _per_joint(0.0)  # mA the last arrival took off, until the joint crosses
    off: np.ndarray = _per_joint(False)  # an arrival's take-off did not hold it: no more
    scale: np.ndarray = _per_joint(1.0)  # of `arrive`: shrinks by `arrive_decay` per push
    crept: np.ndarray = _per_joint(False)  # crept across its goal on the hold (`creep_rate`)


@dataclass
class _Hold:
    """Whether the actor's hold holds an engaged joint (`hold_check`, falls, coasts)."""

    bad: np.ndarray = _per_joint(False)  # it did not: not used again, `fall_gain` on
    jump_from: np.ndarray = _per_joint(math.nan)  # mA: u_i before a jump to the hold, checked
    jump_to: np.ndarray = _per_joint(0.0)  # mA: ... and after it
    jump_age: np.ndarray = _per_joint(0.0)  # s since that jump


@dataclass
class _Fall:
    """The fall and coast watches on an engaged joint (`fall_ramp`, `coast_s`)."""

    away_peak: np.ndarray = _per_joint(0.0)  # rad/s: fastest low-passed speed away, this move
    side: np.ndarray = _per_joint(0.0)  # the side of the goal the joint last fell on
    scale: np.ndarray = _per_joint(1.0)  # of `fall_ramp`: shrinks by `fall_decay` per side
    coast_side: np.ndarray = _per_joint(0.0)  # the side of the goal it was engaged on (0: off)
    engaged_for: np.ndarray = _per_joint(0.0)  # s since it was engaged


@dataclass
class _Latency:
    """The loop's latency, timed from a target's first samples (`onset_*`)."""

    period: float  # s: the control period, measured while timing (`default_dt` before)
    periods: float | None = None  # the latency in periods (None: not yet timed)
    timed: bool = False  # timed from motion (it stays across targets)
    step: int = 0  # samples seen while timing
    clock: float = 0.0  # s since the onset sample
    # at the onset sample: the joints commanded hard, their commands' signs, their positions
    onset: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    # since then: (clock, distance moved the commanded way, speed that way)
    samples: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)

    def time(
        self,
        law: SettleLaw,
        limits_mA: np.ndarray,
        dt: float,
        q: np.ndarray,
        qdot: np.ndarray,
        e: np.ndarray,
        u: np.ndarray,
    ) -> None:
        """One sample. At a target's first, the joints the actor drives hard (`onset_fraction`)
        far from their goals (`onset_error`); `onset_steps` samples later, the earliest of
        their starts after it: each joint is at speed (80 % of its fastest) within about 10 ms
        of its start, so one that moved d at speed v at a sample started d / v before it (a
        weak or heavy joint is late; counting whole periods, all 20 Hz samples show, is off
        by up to one)."""
        self.step += 1
        if self.onset is None:
            hard = (
                (np.abs(u) >= law.onset_fraction * limits_mA)
                & (np.abs(e) >= law.onset_error)
                & (np.sign(u) == np.sign(e))
            )
            self.onset = (hard, np.sign(u) * hard, q.copy())
            if not hard.any():
                self.periods = 0.0  # nothing to time it by; the next target tries
            return
        self.clock += dt
        hard, sign, q0 = self.onset
        self.samples.append((self.clock, sign * (q - q0), sign * qdot))
        if self.step < law.onset_steps:
            return
        starts: list[float] = []
        times = np.array([s[0] for s in self.samples])
        for j in np.flatnonzero(hard):
            moved = np.array([s[1][j] for s in self.samples])
            speed = np.array([s[2][j] for s in self.samples])
            fast = speed >= max(0.3, 0.8 * speed.max())  # at speed: 80 % of the fastest seen
            if not fast.any():
                continue
            k = int(np.argmax(fast))
            if k > 0 and speed[k - 1] < 0.3 * speed[k]:
                # still at the sample before: time the start from the distance since then, so
                # that gravity sag before the command took effect does not read as motion
                starts.append(float(times[k] - (moved[k] - moved[k - 1]) / speed[k]))
            else:
                starts.append(float(times[k] - moved[k] / speed[k]))
        period = float(times[-1]) / len(times)
        self.period = period
        self.periods = max(0.0, min(starts)) / period if starts else 0.0
        self.timed = bool(starts)


@dataclass
class SettleSupervisor:
    """The per-joint state machine: `update` each control step with the actor's command."""

    law: SettleLaw
    limits_mA: np.ndarray
    # What the supervisor did with each joint on this target (`report`):
    engaged: np.ndarray = field(init=False)  # bool: the settle law has it
    reasons: list[Reason] = field(init=False)  # why it was last engaged
    engaged_at: np.ndarray = field(init=False)  # s, the controller's clock: when
    releases: np.ndarray = field(init=False)  # times handed back to the actor
    u_i: np.ndarray = field(init=False)  # mA: the settle law's integral (u_I)
    # Its run-time state, by concern:
    _lp: _Filtered = field(init=False, repr=False)
    _noise: _Noise = field(init=False, repr=False)
    _watch: _Watch = field(init=False, repr=False)
    _ramp: _Ramp = field(init=False, repr=False)
    _arrival: _Arrival = field(init=False, repr=False)
    _hold: _Hold = field(init=False, repr=False)
    _fall: _Fall = field(init=False, repr=False)
    _latency: _Latency = field(init=False, repr=False)
    _target: np.ndarray | None = field(init=False, repr=False)  # the goal (rad)
    _t: float | None = field(init=False, repr=False)  # s: the last sample's time
    _u_goal: np.ndarray | None = field(init=False, repr=False)  # mA: the actor's hold there
    # from the law: the joints whose crossing watch stays on a prompt loop, and those whose
    # reversing watch is on (`prompt_joints`)
    _prompt_watch: np.ndarray = field(init=False, repr=False)
    _reverse_watch: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.limits_mA = np.asarray(self.limits_mA, dtype=float)
        watched = self.law.prompt_joints if self.law.crossing_on_prompt_loop else ""
        self._prompt_watch = np.array([letter in watched for letter in JOINT_LETTERS])
        self._reverse_watch = np.array([x in self.law.prompt_joints for x in JOINT_LETTERS])
        self.reset()

    def reset(self) -> None:
        n = N_JOINTS
        self.engaged = np.zeros(n, dtype=bool)
        self.reasons = [Reason.NONE] * n
        self.engaged_at = np.full(n, math.nan)
        self.releases = np.zeros(n, dtype=int)
        self.u_i = np.zeros(n)
        window = max(1, int(round(self.law.jitter_window_s / self.law.default_dt)))
        self._lp = _Filtered()
        self._noise = _Noise()
        self._watch = _Watch(np.zeros((window, n)))
        self._ramp = _Ramp()
        self._arrival = _Arrival()
        self._hold = _Hold()
        self._fall = _Fall()
        self._latency = _Latency(self.law.default_dt)
        self._target = None
        self._t = None
        self._u_goal = None

    @property
    def latency_periods(self) -> float | None:
        """The loop's latency in control periods, as timed (None before it has been)."""
        return self._latency.periods

    @property
    def e_f(self) -> np.ndarray:
        """The low-passed error to the goal (rad), per joint."""
        return self._lp.e

    @property
    def v_f(self) -> np.ndarray:
        """The low-passed speed (rad/s), per joint."""
        return self._lp.v

    @property
    def u_f(self) -> np.ndarray:
        """The low-passed actor command (mA), per joint."""
        return self._lp.u

    def report(self) -> dict[str, Any]:
        """What the supervisor did on the current target: the latency it timed (periods, None
        before it has) and each joint it engaged, why, when (the controller's clock, s) and
        how often it was released back to the actor."""
        engaged = {
            JOINT_LETTERS[j]: {
                "reason": self.reasons[j].value,
                "at_s": float(self.engaged_at[j]),
                "releases": int(self.releases[j]),
            }
            for j in range(N_JOINTS)
            if self.engaged[j] or self.releases[j] > 0
        }
        latency = None if self.latency_periods is None else float(self.latency_periods)
        return {"latency_periods": latency, "engaged": engaged}

    def _new_target(self, target: np.ndarray) -> None:
        # the latency is the loop's, not the target's: once timed from motion it stays
        timed = self._latency
        self.reset()
        if timed.timed:
            self._latency = _Latency(timed.period, timed.periods, True)
        self._target = target.copy()

    def update(
        self,
        t: float | None,
        q: np.ndarray,
        qdot: np.ndarray,
        target: np.ndarray,
        u: np.ndarray,
        u_goal: np.ndarray | None = None,
    ) -> np.ndarray:
        """The currents to send: `u` (the actor's) on joints not engaged, the settle law's on
        the others."""
        law = self.law
        if self._target is None or np.any(target != self._target):
            self._new_target(target)
        dt = law.default_dt
        if t is not None and self._t is not None and 0 < t - self._t <= 4 * law.default_dt:
            dt = float(t) - self._t
        self._t = None if t is None else float(t)
        now = self._t if self._t is not None else 0.0
        e = target - q
        a = min(1.0, dt / law.filter_s)
        lp = self._lp
        lp.e = np.where(lp.fresh, e, lp.e + a * (e - lp.e))
        lp.v = np.where(lp.fresh, qdot, lp.v + a * (qdot - lp.v))
        b = min(1.0, dt / law.hold_filter_s)
        lp.u = np.where(lp.fresh, u, lp.u + b * (u - lp.u))
        lp.fresh[:] = False
        v_last = self._noise.v_prev.copy()
        self._estimate_noise(dt, e, qdot)
        near = np.abs(e) < law.band
        watch = self._watch
        watch.v2[watch.v2_n % watch.v2.shape[0]] = qdot**2
        watch.v2_n += 1
        self._u_goal = u_goal
        latency = self._latency
        latent = law.latent_crossing_speed > 0 and law.crossing_speed > 0
        if latent and latency.periods is None:
            latency.time(law, self.limits_mA, dt, q, qdot, e, u)
        crossing_speed = np.full(N_JOINTS, law.crossing_speed)
        ahead = -1.0
        if latent and (latency.periods or 0.0) >= law.latent_periods:
            crossing_speed[:] = law.latent_crossing_speed
            if law.latent_ahead >= 0:
                ahead = ((latency.periods or 0.0) + law.latent_ahead) * latency.period
        elif latent and latency.timed:
            # timed without latency: an overshoot is the actor's own, but on those joints
            crossing_speed[~self._prompt_watch] = 0.0
        out = np.asarray(u, dtype=float).copy()
        for j in range(N_JOINTS):
            if self.engaged[j] and abs(e[j]) > law.release:
                self._release(j)
            if not self.engaged[j]:
                self._watch_joint(j, now, dt, near[j], e[j], u[j], qdot[j])
            reversed_ = qdot[j] * v_last[j] < 0 and self._reverse_watch[j] and near[j]
            fast = min(abs(qdot[j]), abs(v_last[j])) >= law.reversing_speed > 0
            if not self.engaged[j] and reversed_ and fast:
                self._engage(j, now, Reason.REVERSING)
            if not self.engaged[j] and crossing_speed[j] > 0:
                crossed = watch.e_prev[j] * e[j] < 0
                if crossed and abs(qdot[j]) >= crossing_speed[j]:
                    self._engage(j, now, Reason.CROSSING)
                elif ahead >= 0 and near[j] and abs(qdot[j]) >= crossing_speed[j]:
                    if (e[j] - qdot[j] * ahead) * e[j] < 0:
                        self._engage(j, now, Reason.CROSSING_AHEAD)
            watch.e_prev[j] = e[j]
            if self.engaged[j]:
                out[j] = self._settle(j, dt, e[j], qdot[j])
        return out

    def _estimate_noise(self, dt: float, e: np.ndarray, qdot: np.ndarray) -> None:
        """Position and speed noise per joint from second (position) and first (speed)
        differences of successive samples while the joint is slow, where noise dominates
        them: var(e_k - 2 e_k-1 + e_k-2) = 6 var(e), var(v_k - v_k-1) = 2 var(v)."""
        noise = self._noise
        slow = np.abs(self._lp.v) < self.law.stuck_speed
        a = min(1.0, dt / NOISE_FILTER_S)
        dd = e - 2 * noise.q_hist[1] + noise.q_hist[0]
        ok = slow & np.isfinite(dd)
        noise.q_var = np.where(ok, noise.q_var + a * (dd**2 / 6 - noise.q_var), noise.q_var)
        dv = qdot - noise.v_prev
        ok = slow & np.isfinite(dv)
        noise.v_var = np.where(ok, noise.v_var + a * (dv**2 / 2 - noise.v_var), noise.v_var)
        noise.v_w = np.where(ok, noise.v_w + a * (1.0 - noise.v_w), noise.v_w)
        noise.q_hist = np.stack([noise.q_hist[1], e.astype(float)])
        noise.v_prev = np.asarray(qdot, dtype=float).copy()

    def _watch_joint(
        self, j: int, now: float, dt: float, near: bool, e: float, u: float, qdot: float
    ) -> None:
        """The watches on a joint the actor holds (module docstring): engage it, or not."""
        law = self.law
        watch = self._watch
        if law.stuck and not near and abs(e) < law.stuck_band:
            self._watch_stuck(j, now, dt, qdot)
            return
        if not near:
            watch.sign[j] = 0.0
            watch.rev_count[j] = 0
            watch.stuck_for[j] = 0.0
            watch.held_for[j] = 0.0
            watch.in_band_for[j] = 0.0
            return
        if law.cycles and abs(u) >= law.reversal_fraction * self.limits_mA[j]:
            sign = math.copysign(1.0, u)
            if watch.sign[j] != 0.0 and sign != watch.sign[j]:
                if not now - watch.rev_last[j] <= law.max_gap_s:
                    watch.rev_start[j], watch.rev_count[j] = now, 0
                watch.rev_last[j] = now
                watch.rev_count[j] += 1
                span = now - watch.rev_start[j]
                if watch.rev_count[j] >= law.reversals and span >= law.min_span_s - 1e-9:
                    self._engage(j, now, Reason.CYCLING)
                    return
            watch.sign[j] = sign
        if law.jitter_speed > 0:
            inside = abs(e if law.jitter_raw else self._lp.e[j]) < law.jitter_band
            watch.in_band_for[j] = watch.in_band_for[j] + dt if inside else 0.0
            if watch.in_band_for[j] >= law.jitter_s - 1e-9 and watch.v2_n >= watch.v2.shape[0]:
                rms = math.sqrt(float(np.mean(watch.v2[:, j])))
                if rms > self._jitter_limit():
                    self._engage(j, now, Reason.JITTER)
                    return
        if law.hold_s > 0:
            settled = abs(self._lp.e[j]) < law.hold_error
            watch.held_for[j] = watch.held_for[j] + dt if settled else 0.0
            if watch.held_for[j] >= law.hold_s - 1e-9:
                self._engage(j, now, Reason.HOLD)
                return
        if law.stuck:
            self._watch_stuck(j, now, dt, qdot)

    def _jitter_limit(self) -> float:
        """The jitter watch's threshold: `jitter_speed`, or lower on a quiet arm, where true
        speed of `jitter_true_speed` shows over the noise (`jitter_noise_k` sigma of it). The
        noise is the arm's sensors', so the quietest joint whose estimate has settled (80 %
        of its weight: 1.6 s of slow samples) gives it; a dithering joint's own is inflated."""
        law = self.law
        noise = self._noise
        settled = noise.v_w >= NOISE_SETTLED
        if law.jitter_true_speed <= 0 or not settled.any():
            return law.jitter_speed
        sigma = math.sqrt(float(np.min(noise.v_var[settled] / noise.v_w[settled])))
        return min(law.jitter_speed, math.hypot(law.jitter_true_speed, law.jitter_noise_k * sigma))

    def _noise_floors(self, j: int, dt: float) -> tuple[float, float]:
        """What the sensors' noise can explain, `noise_sigmas` of it: of the low-passed speed
        and of a change in the low-passed error (an EMA of gain a keeps a / (2 - a) of its
        samples' variance; a difference of two of them, twice that)."""
        a = min(1.0, dt / self.law.filter_s)
        shrink = a / (2 - a)
        speed = self.law.noise_sigmas * math.sqrt(shrink * self._noise.v_var[j])
        moved = self.law.noise_sigmas * math.sqrt(2 * shrink * self._noise.q_var[j])
        return speed, moved

    def _slipping(self, j: int, e: float, qdot: float) -> bool:
        """One sample's measured speed towards the goal beyond what the noise explains."""
        law = self.law
        floor = max(2 * law.stuck_speed, law.noise_sigmas * math.sqrt(self._noise.v_var[j]))
        return math.copysign(1.0, e) * qdot >= floor

    def _watch_stuck(self, j: int, now: float, dt: float, qdot: float) -> None:
        law = self.law
        watch = self._watch
        e_f = self._lp.e
        slow = abs(self._lp.v[j]) < max(law.stuck_speed, self._noise_floors(j, dt)[0])
        if slow and law.raw_breakaway:  # not a joint that has just begun to slip
            slow = not self._slipping(j, e_f[j], qdot)
        still = abs(e_f[j]) > law.stuck_error and slow
        if still and watch.stuck_for[j] > 0 and law.creep_arrive_s > 0:
            # creeping in slower than the noisy speed can show: the low-passed error has
            # shrunk since the watch began by more than the noise explains, fast enough to
            # arrive within `creep_arrive_s` (a slower creep is as good as stuck)
            shrunk = watch.stuck_e0[j] - abs(e_f[j])
            moved = max(law.progress, self._noise_floors(j, dt)[1])
            soon = abs(e_f[j]) * watch.stuck_for[j] / law.creep_arrive_s
            if shrunk > moved and shrunk >= soon:
                still = False
        if still and watch.stuck_for[j] == 0:
            watch.stuck_e0[j] = abs(e_f[j])
        watch.stuck_for[j] = watch.stuck_for[j] + dt if still else 0.0
        if watch.stuck_for[j] >= law.stuck_s - 1e-9:
            self._engage(j, now, Reason.STUCK)

    def _engage(self, j: int, now: float, why: Reason) -> None:
        self.engaged[j] = True
        self.reasons[j] = why
        self.engaged_at[j] = now
        # The actor's hold on the goal; but a joint stuck short is at rest under the actor's
        # steady command, which holds it there (on a weak joint, several times the nominal
        # hold), so it starts from that low-passed command, as does a supervisor used without
        # an actor (u_goal not given).
        if self._u_goal is None or why is Reason.STUCK:
            self.u_i[j] = self._lp.u[j]
        elif why is Reason.JITTER:
            self._to_hold(j, float(self._u_goal[j]), self._lp.u[j])
        elif not (self.law.fall_memory and self._hold.bad[j]):
            self.u_i[j] = float(self._u_goal[j])
        self._ramp.ramped[j] = 0.0
        self._ramp.was_stuck[j] = False
        self._ramp.brk_pending[j] = False  # a breakaway before a release is not this one's
        self._arrival.crept[j] = False
        # a joint stuck short is at rest, not coasting: only the others are watched (`coast_s`)
        coast_side = 0.0 if why is Reason.STUCK else math.copysign(1.0, self._lp.e[j])
        self._fall.coast_side[j] = coast_side
        self._fall.engaged_for[j] = 0.0

    def _to_hold(self, j: int, hold: float, alt: float) -> None:
        """u_i to the actor's hold, checked (`hold_check`) against `alt`, what held it so far."""
        held = self._hold
        if held.bad[j]:
            self.u_i[j] = alt
            return
        self.u_i[j] = hold
        if abs(hold - alt) < self.law.creep_hold * self.limits_mA[j]:
            return  # about the same: nothing to check
        held.jump_from[j] = alt
        held.jump_to[j] = hold
        held.jump_age[j] = 0.0

    def _release(self, j: int) -> None:
        self.engaged[j] = False
        self.releases[j] += 1
        self._watch.sign[j] = 0.0
        self._watch.rev_count[j] = 0
        self._watch.rev_last[j] = math.nan
        self._watch.stuck_for[j] = 0.0

    def _fall_watch(self, j: int, dt: float, ef: float, floor: float) -> None:
        """`fall_ramp`: a joint outside `band` moving away from its goal at the fastest it has
        since it began to (within `floor`), not slowing as a coast through the goal does, is
        falling: what it is on does not hold it."""
        law = self.law
        fall = self._fall
        away = -math.copysign(1.0, ef) * self._lp.v[j]
        fall.away_peak[j] = 0.0 if away < floor else max(fall.away_peak[j], away)
        if abs(ef) <= law.band or away < floor or away < fall.away_peak[j] - floor:
            return
        side = math.copysign(1.0, ef)
        if fall.side[j] == -side:  # the last fall's ramp carried it through its goal
            fall.scale[j] *= law.fall_decay
        fall.side[j] = side
        self._hold.bad[j] = True
        rate = law.fall_ramp * fall.scale[j] * law.ramp[j] * self.limits_mA[j]
        self.u_i[j] += side * rate * dt

    def _coast(self, j: int, ef: float, floor: float) -> None:
        """`coast_s`: a joint still moving away from its goal that long after its engagement,
        that far past it, is one on which the soft gains act as a fraction of themselves. The
        watch ends there, or once the joint is seen coming back after `coast_s`."""
        law = self.law
        fall = self._fall
        if fall.engaged_for[j] < law.coast_s - 1e-9:
            return
        past = -fall.coast_side[j] * ef  # > 0: on the far side of the goal
        away = -math.copysign(1.0, ef) * self._lp.v[j]
        if past > law.coast_band and away >= floor:
            self._hold.bad[j] = True
            fall.coast_side[j] = 0.0
        elif away <= -floor:
            fall.coast_side[j] = 0.0

    def _confirm(self, j: int, ef: float, slow: bool, progress: float) -> None:
        """`restick_s` after a breakaway: a joint that is slow and further from its goal than
        where its ramp began, by more than the noise explains (`progress`), did not break
        away; noise said it did. Its backoff is given back and its ramp goes on where it
        stood."""
        ramp = self._ramp
        away = ramp.side[j] * ef - ramp.stuck_from[j]  # < 0: nearer, or through
        if away > progress and slow and not ramp.was_stuck[j]:
            k = 0 if ramp.side[j] > 0 else 1
            self.u_i[j] += self.law.backoff * ramp.brk_ramped[j]
            ramp.ramped[j] = ramp.brk_ramped[j]
            ramp.break_u[j, k] = ramp.brk_prev[j]
            ramp.was_stuck[j] = True
        ramp.brk_pending[j] = False

    def _settle(self, j: int, dt: float, e: float, qdot: float) -> float:
        """The settle law's command for engaged joint `j` (module docstring)."""
        law = self.law
        ramp, arrival, held = self._ramp, self._arrival, self._hold
        limit = self.limits_mA[j]
        ef = self._lp.e[j]
        v_f = self._lp.v[j]
        if abs(ef) > law.freeze or abs(v_f) >= law.stuck_speed:
            gain = law.fall_gain if held.bad[j] else 1.0
            self.u_i[j] += gain * law.ki[j] * e * dt
        may_ramp = law.stuck if self.reasons[j] is Reason.STUCK else law.ramp_engaged
        speed_floor, moved_floor = self._noise_floors(j, dt)
        moving = max(law.stuck_speed, speed_floor)  # a low-passed speed beyond the noise
        slow = abs(v_f) < moving
        # Breakaway: the low-passed speed, or (`progress` > 0) the low-passed error having
        # shrunk by `progress` since the ramp began; a joint creeping in slower than the noisy
        # speed can show has broken away too, and ramping on would carry it through its goal.
        progress = max(law.progress, moved_floor)
        moved = law.progress > 0 and abs(ef) < ramp.stuck_from[j] - progress
        toward = math.copysign(1.0, ef) * v_f  # > 0: moving towards the goal
        broke = toward >= moving or moved
        if law.raw_breakaway and not broke:
            broke = self._slipping(j, ef, qdot)
        if law.freeze_breakaway and abs(ef) <= law.freeze:
            # ramped in from outside `stuck_error` to inside `freeze`: it broke away, though
            # on a noisy sensor `progress` may not have said so yet
            broke = True
        ramp.since_break[j] += dt
        if law.hold_check and math.isfinite(held.jump_from[j]):
            held.jump_age[j] += dt
            window = ((self.latency_periods or 0.0) + 4.0) * self._latency.period
            d = math.copysign(1.0, held.jump_to[j] - held.jump_from[j])
            if d * v_f >= moving and d * qdot >= moving:
                self.u_i[j] += held.jump_from[j] - held.jump_to[j]
                held.bad[j] = True
                held.jump_from[j] = math.nan
            elif held.jump_age[j] > window + 1e-9:
                held.jump_from[j] = math.nan
        if law.fall_ramp > 0:
            self._fall_watch(j, dt, ef, moving)
        self._fall.engaged_for[j] += dt
        if law.coast_s > 0 and self._fall.coast_side[j] != 0:
            self._coast(j, ef, moving)
        if ramp.brk_pending[j] and ramp.since_break[j] >= law.restick_s - 1e-9:
            self._confirm(j, ef, slow, progress)
        if ramp.was_stuck[j] and broke:
            ramp.since_break[j] = 0.0
            k = 0 if ramp.side[j] > 0 else 1
            if law.confirm_breakaway and abs(ef) > law.freeze:
                ramp.brk_pending[j] = True
                ramp.brk_ramped[j] = ramp.ramped[j]
                ramp.brk_prev[j] = ramp.break_u[j, k]
            ramp.break_u[j, k] = self.u_i[j]
            self.u_i[j] -= law.backoff * ramp.ramped[j]
            ramp.ramped[j] = 0.0
            ramp.was_stuck[j] = False
        elif (
            may_ramp
            and abs(ef) > law.stuck_error
            and slow
            and ramp.since_break[j] >= law.restick_s - 1e-9
        ):
            if not ramp.was_stuck[j]:
                self._start_ramp(j, ef, limit)
            rate = law.ramp[j] * ramp.scale[j] * ramp.rate[j]
            if law.ramp_grow[j] > 0:
                rate *= 1.0 + abs(ramp.ramped[j]) / (law.ramp_grow[j] * limit)
            step = math.copysign(rate * limit * dt, ef)
            self.u_i[j] += step
            ramp.ramped[j] += step
            ramp.was_stuck[j] = True
        if abs(ef) <= law.freeze:
            ramp.ramped[j] = 0.0
            ramp.was_stuck[j] = False
        # An arrival is armed outside twice `stuck_error` and spent once the joint is inside
        # `stuck_error`: taken off if it creeps in, or left alone if it comes to rest there.
        # Only on a joint engaged because it was stuck: friction holds it, not its command.
        stuck = self.reasons[j] is Reason.STUCK
        if law.arrive > 0 and stuck and abs(ef) > 2 * law.stuck_error:
            if law.arrive_check and arrival.took[j] != 0 and arrival.took[j] * ef > 0:
                # back out on the side it arrived from, not across: what was taken off held it
                self.u_i[j] += arrival.took[j]
                arrival.took[j] = 0.0
                arrival.off[j] = True
            arrival.arriving[j] = not arrival.off[j]
        elif arrival.arriving[j] and abs(ef) < law.stuck_error:
            if toward > max(0.5 * law.stuck_speed, speed_floor):
                took = math.copysign(law.arrive * limit * arrival.scale[j], ef)
                self.u_i[j] -= took
                arrival.took[j] = took
                arrival.arriving[j] = False
            elif slow:
                arrival.arriving[j] = False
        if abs(ef) > law.freeze:
            side = math.copysign(1.0, ef)
            if arrival.side[j] == -side:  # crossed its goal since it was last outside `freeze`
                arrival.took[j] = 0.0
                hold = None if self._u_goal is None else float(self._u_goal[j])
                if slow and hold is not None and abs(self.u_i[j] - hold) < law.creep_hold * limit:
                    # crept across on about the actor's hold, no ramp pushing it: friction is weak
                    arrival.crept[j] = True
                if law.arrive > 0 and stuck:
                    # crept across the goal (not ramping: a ramp's breakaway has its backoff)
                    self.u_i[j] += side * law.arrive * limit * arrival.scale[j]
                    arrival.scale[j] *= law.arrive_decay
            arrival.side[j] = side
        self.u_i[j] = float(np.clip(self.u_i[j], -limit, limit))
        gain = law.fall_gain if held.bad[j] else 1.0
        cmd = self.u_i[j] + gain * (law.kp[j] * e - law.kd[j] * qdot)
        return float(np.clip(cmd, -limit, limit))

    def _start_ramp(self, j: int, ef: float, limit: float) -> None:
        """A stuck ramp begins on side sign(ef): its rate, and where it starts from (the
        actor's hold if it must push back across a wide friction band, `reverse_to_hold`; near
        where it last broke away this way, `memory_margin`)."""
        law = self.law
        ramp = self._ramp
        ramp.stuck_from[j] = abs(ef)
        side = math.copysign(1.0, ef)
        if ramp.side[j] == -side:  # the last breakaway carried it through
            ramp.scale[j] = max(law.ramp_floor, law.ramp_decay * ramp.scale[j])
        ramp.side[j] = side
        brk = ramp.break_u[j, 0 if side > 0 else 1]
        ramp.rate[j] = law.creep_rate if self._arrival.crept[j] else 1.0
        hold = None if self._u_goal is None else float(self._u_goal[j])
        other = ramp.break_u[j, 1 if side > 0 else 0]  # broke away the other way at
        if (
            law.reverse_to_hold > 0
            and hold is not None
            and side * (hold - self.u_i[j]) > 0
            and abs(other - hold) >= law.reverse_to_hold * limit
        ):
            # still pushing the other way across a wide friction band (carried through
            # its goal): start from the hold (not ramp: the backoff leaves it alone)
            self._to_hold(j, hold, self.u_i[j])
        if law.memory_margin >= 0 and math.isfinite(brk):
            # it broke away at `brk` last time: the ramp need not climb from below
            jump = brk - side * law.memory_margin * limit - self.u_i[j]
            if side * jump > 0:
                self.u_i[j] += jump
                ramp.ramped[j] += jump
                ramp.rate[j] = law.memory_rate
