"""A per-joint settle supervisor around the DDPG actor: engineered, not learned.

The actor is stateless and has one near-goal gain for every arm. On an arm with 1-2 periods of
control latency and little Coulomb friction that gain drives a joint into a limit cycle around
its goal, and on a light joint (B) or under 2-3x sensor noise it jitters at the goal
(docs/robustness.md). This layer watches every joint near its goal and hands *that joint* to a
conservative settle law when it sees the signature, until the target changes or the joint
leaves `release` of its goal (then it is the actor's again, and watched again). The approach,
and every joint that settles normally, stay the actor's: on Table I's standard episodes (seed
2020) it never engages. It ships in `ddpg`; `ddpg --param settle=0` turns it off and
`ddpg-pure` has none (docs/robustness.md, "The settle supervisor").

Watching (per joint, within `band` of the goal):

- **cycling**: the actor's command reverses sign at `reversal_fraction` of the joint's
  current limit or more, `reversals` times with no gap over `max_gap_s` between them and over
  at least `min_span_s` (an arrival that brakes reverses 2-4 times in 0.1-0.15 s, docs/metrics.md
  "Rest"; a limit cycle of period ~0.4 s reverses twice per period);
- **crossing** (`crossing_speed` > 0): the joint crosses its goal at `crossing_speed` or
  faster (0.8 rad/s, two thirds of the no-load speed). The actor brakes its arrivals before the
  goal; with 1-2 periods of latency it brakes on a state already that old, crosses at full
  speed and starts the cycle that the reversal watch sees only one or two swings later, each
  swing 2-3 J spent after the joint counts as settled. On a loop whose latency is timed at
  `latent_periods` (0.2) or more, a joint crossing at `latent_crossing_speed` (0.15 rad/s) is
  engaged: there a crossing at any speed is the first swing of the cycle, and E arriving
  unbraked at 1-2 periods spent 0.6-1.1 J in that swing before it reached 0.8 rad/s. On a
  loop timed below that, `crossing_on_prompt_loop` (on) keeps the 0.8 rad/s watch on E, D
  and C (`prompt_joints`): it catches frictionless heavy rotors early. Not on B: there it took
  B on one of Table I's seed-2120 episodes (crossing at 1.15 rad/s), which the soft law
  settled 0.8 s later than the actor would;
  on a latent loop a joint is also engaged *before* it crosses, once it will cross at that
  speed within the latency plus `latent_ahead` (1) periods: the commands already in flight
  carry it that far, and a crossing seen only once it has happened was a full-speed swing
  through the settling band (0.4-0.7 J spent after the joint counted as settled);
- **reversing** (`reversing_speed` > 0, E D C: `prompt_joints`): the measured speed reverses
  between two samples, `reversing_speed` (0.5 rad/s) or faster both ways. On a prompt loop
  the actor bang-bangs a strong frictionless joint at its goal at the no-load speed each way
  (+1.17, -0.75, +1.17, -1.17 rad/s on E), within its band and short of its goal, so the
  crossing watch sees it only once it crosses, 0.5 J later; noise does not reverse that fast,
  and a braked arrival does not reverse at all;
- **jitter** (`jitter_speed` > 0): after `jitter_s` (1 s) with the reading's error within
  `jitter_band` (`jitter_raw`: the low-passed error lags a fast arrival), the RMS of
  the measured speed over the last `jitter_window_s` (0.5 s, so that an arrival's last swing
  inside the band falls before it) exceeds `jitter_speed` (the sensor noise alone gives
  0.02-0.06 rad/s). At 1.5 s and 1 s an actor kicking a joint at its goal on a noisy arm
  spent over 0.5 J before it was taken. On a quiet arm the threshold is lower: once the
  sensors' speed noise sigma is estimated (the quietest joint's), it is hypot(
  `jitter_true_speed`, `jitter_noise_k` sigma) if that is less, 0.054 rad/s at 1x noise:
  there the actor dithered frictionless joints at 0.05-0.07 rad/s of true speed, more than
  the rest metric allows, and through the noise that read under 0.08;
- **stuck short** (`stuck`; out to `stuck_band`, 0.5 rad, since a weak joint held by
  friction stops 0.15-0.25 rad short): the low-passed error stays above `stuck_error` and the
  low-passed speed below `stuck_speed` (or what the noise can explain, below) for `stuck_s`,
  and the low-passed error has not shrunk by more than the noise explains since the watch
  began, at a rate that would bring it in within `creep_arrive_s` (4 s): a joint creeping in
  slower than its noisy speed can show is not stuck, and engaged on the actor's command that
  moved it, it slid on through its goal; a creep that slow takes the rest of the episode.

Noise: each joint's position and speed noise is estimated from successive samples while it is
slow (second and first differences). A breakaway, and a joint that is not slow, is a move of
`noise_sigmas` (3) standard deviations of the low-passed signal or more: at 3x the sensor
noise the low-passed speed alone wanders +-0.02 rad/s and the fixed 0.03 rad/s read a joint
stuck for 10 s as moving (the stuck watch never engaged it) and a ramp as broken away.

Latency: at a target's first step the actor drives every joint far from its goal hard; each
drive is at speed within about 10 ms, so a joint that has moved ``d`` at speed ``v`` at a later
sample started ``d / v`` before it, and the earliest joint's start after that first command is
the loop's latency (a weak or heavy joint accelerates late; a joint still at rest at the sample
before is timed from there, so gravity sag before the command took effect does not count).
On 300 envelope draws (0-2 periods, noise 1-3x, armature x0.5-1.5) it comes out 0.05 period
late on average, SD 0.12, never off by 0.5; counting whole periods, all that 20 Hz samples
show directly, is off by up to one. It is timed once per loop (again only if a target gave
nothing to time it by).

The settle law (currents, mA, per joint) is ``u = u_I + kp e - kd qdot``:

- ``u_I`` starts at the actor's own command at rest on the goal (what the network learned holds
  the joint there against gravity and buoyancy; the mean of a cycling command, the old start,
  is arbitrary and drove engaged joints away) and integrates ``ki e``; a joint engaged because
  it is stuck short starts instead from the actor's low-passed command, which was holding it
  at rest there (D at 30 % torque starting from the nominal hold fell back 0.13 rad);
  the gains keep 35 degrees of phase margin and a gain margin of 2 over the envelope's joints
  with 25-130 ms of loop delay (`DEFAULT_*` in `policy.controllers.settle_law`), which makes them
  soft: 2-4 N m/rad. An engaged joint mid-swing may coast well past its goal under them, so it is
  released only beyond `release` (0.5 rad): handing it back to the actor restarted the cycle;
- while the joint is stuck outside `stuck_error` it also ramps at `ramp` (fraction of the
  current limit per second) towards the goal, so that Coulomb friction (6.6 N m is 330 mA on
  E D C) is overcome in a few seconds; at breakaway, `backoff` of the ramp added since it
  stuck is taken back (the excess over breakaway would otherwise carry it through).
  Breakaway is the low-passed speed reaching `stuck_speed` or the low-passed error shrinking
  by `progress` since the ramp began: a joint creeping in at 0.01 rad/s is below what the
  noisy speed can show, and ramping on drove a slow stick-slip cycle across the goal. A ramp
  fast enough for 6.6 N m breaks a joint with 0.2 N m away with several times its friction,
  and with latency it sticks again on the other side: each time that happens the joint's
  ramp rate is multiplied by `ramp_decay` (0.7, with no floor: `ramp_floor` 0), so the
  hunting dies out while a high-friction joint still breaks away in seconds. On B the rate
  also grows with what the ramp has added since the joint stuck (`ramp_grow`: doubled after
  10 % of the limit, 30 mA; a memory restart's jump counts): B's ramp is slow, and a weak
  B's friction is 90 mA of its command. Breakaway counts only towards the goal (a joint
  slipping away from it under gravity has not broken free of the ramp). With `raw_breakaway`
  a single sample of measured speed towards the goal beyond what the noise explains is a
  breakaway too, and stops the stuck watch engaging a joint that has just begun to slip
  (engaged on the actor's low-passed command, one slid 0.12 rad, past its goal): the
  low-passed speed sees a slip 2-3 periods late, and with 1-2 periods of latency the ramp's
  command swung a 6 N m joint 0.05 rad, from one side of its goal to the other, each time: a
  hunt across the tolerance at 0.1-0.3 J a swing;
- breakaway memory: where friction holds, the backoff leaves the joint well inside its
  friction band and a re-ramp climbed the whole band again (7 s on a weak D). A joint that
  sticks again on the side it broke away from restarts `memory_margin` (5 % of the limit)
  below the command it broke away at, and ramps at `memory_rate` (0.3) of the rate from there:
  the push past breakaway grows with the rate, and with it the step the joint makes;
- a breakaway refuted: one sample of speed noise towards the goal (3 sigma, `raw_breakaway`)
  reads as a breakaway once in about 740 samples of Gaussian noise (37 s at 20 Hz), and its
  backoff takes 80 % of the ramp back. `restick_s` after a breakaway, a joint that is slow
  and further from its goal than where its ramp began, by more than the noise explains, did
  not break away: the backoff is given back, its ramp goes on from where it stood and the
  memory keeps the breakaway before (`confirm_breakaway`: a weak B creeping away from its
  goal while its ramp caught up lost its ramp that way twice and ended just outside the
  tolerance). Only further away: a joint merely no nearer is common where friction holds
  (seen breaking away late, it has made its step and stuck again), and at three times the
  noise giving such joints their backoff back drove 6.6 N m joints through their goals (9
  of the corners of the twin whose friction holds lost, 0.5-1.4 J after settling);
- reversing: a joint whose breakaway carried it through its goal sticks on the far side
  still commanded the first way, a whole friction band (2 x 300 mA at 6 N m) from pushing
  back; its ramp starts from the actor's hold at the goal instead (D engaged on the actor's
  330 mA, broken away before the backoff had anything to take back, took the rest of the
  episode to ramp down from +306 mA), where the joint broke away the first way
  `reverse_to_hold` (a quarter of the limit, 3 N m on E D C) or more from that hold: the
  hold is the actor's, learned on the model, and on a joint with little friction the jump to
  it was a kick (done everywhere, 81.7 % of the corners reached instead of 90.8 %);
- arrival: a joint engaged because it was stuck rests on a command near breakaway; on one just
  past it, it creeps on through its goal and sticks beyond, a whole friction band away from
  coming back. Creeping into `stuck_error` of the goal (armed outside twice that), `arrive`
  (5 % of the limit) is taken off its command once; creeping across the goal, the same is
  pushed back towards it, each push `arrive_decay` (half) of the one before (a weak D on
  a frictionless arm, pushed 30 mA each time it crept across, hunted about its goal to
  the end: 5 more corners reached, one lost). Only on joints engaged as stuck: on a joint
  with little friction the same 5 % is a kick (measured: 93.8 % instead of 97.9 % when it
  applied to every joint that had ramped). And after a breakaway the ramp waits `restick_s`
  before it may start again: the low-passed error lags a creeping joint, and a ramp
  restarted on that lag pushed a joint in at 0.08 rad/s 20 mrad through its goal;
- inside `freeze` (low-passed error) a joint at rest does not integrate: one held by friction
  inside the tolerance is left alone instead of hunting (one still drifting through the band
  integrates on, or a stale u_I carries it out the other side). A ramping joint that reaches
  `freeze` has broken away (`freeze_breakaway`), like any other breakaway (the backoff, the
  command it broke away at for the memory, the wait of `restick_s`): on a noisy sensor
  `progress` may need as much movement as lies between `stuck_error` and `freeze`, and
  forgetting the ramp there left its excess pushing the joint through its goal;
- checking the hold: the actor's hold is learned on the model; on a weak joint (25 % torque)
  carrying 20 % more mass it is a fraction of what holds the joint (C: -16 mA where -60
  did), and a joint moved onto it falls (D at 25 % dropped 0.4 rad, 2 s before the end, and
  was missed). So a joint moved to the hold from a command that held it (the jump of
  `reverse_to_hold`, or an engagement for jitter, which starts from the hold instead of the
  low-passed actor command) is watched for its latency plus four periods: if it moves the way
  of that change, low-passed and measured speed both beyond the noise (`hold_check`), the
  change is undone and the joint's hold is not used again on that target (12 of the 896
  corners reached that were missed, none lost; draws and Table I unchanged);
- falling: a joint engaged on the actor's hold as it crosses its goal is already moving when
  the hold takes over, so the hold check cannot see it fall; a weak one does (C at 25 %
  torque, engaged at 1 rad/s on the actor's hold, 68 mA short of what holds it, fell 0.5 rad,
  was released to the actor, driven back through its goal and engaged again, six times). An
  engaged joint outside `band` moving away from its goal at the fastest it has since it began
  to (within the noise: a coast through the goal slows from its crossing speed at once, a fall
  does not) ramps towards the goal at `fall_ramp` of the stuck ramp's rate, and its hold is
  not used again on that target; engaged again after a release it keeps the u_i it had
  (`fall_memory`). The ramp runs on for the latency and the filter's lag and may carry it
  through: each fall on the other side of the goal from the last one ramps at `fall_decay` of
  the rate before. Calling a joint falling whenever its low-passed speed away had not dropped
  since the last sample ramped coasting joints on their noise (3 corners lost). Such a joint
  is weak or heavy, and at 25 % torque the soft gains act as a quarter of themselves: they
  swung a weak C about its goal with a period of 8 s (0.34, 0.28, 0.16, 0.08 rad out); on a
  joint whose hold is marked bad they are `fall_gain` (2) times as stiff (9 more of the
  corners reached, none lost; 3 or 4 times reached none of the rest);
- coasting: a weak joint need not fall to show it. Engaged as it crossed its goal at 1 rad/s,
  a frictionless C at 25 % torque coasted 0.28-0.36 rad past it under the soft gains, swung
  back and forth for the rest of the episode and was kicked on by the stuck ramp at each
  turn (5 corners ended 20-40 mrad out). A joint still moving away from its goal `coast_s`
  (0.7 s) after it was engaged, beyond `coast_band` (0.2 rad) on the far side, is marked as
  one whose hold failed, and gets `fall_gain` too: no strong joint went more than 0.26 rad
  past, and nearly all turned within 0.55 s;
- a take-off that held: on a frictionless weak joint the arrival's `arrive` take-off is what
  held it up (a weak D taken 30 mA off as it crept in fell back 0.1 rad, crept in again
  over 4 s and was taken off again, to the end). A joint that backs out of twice
  `stuck_error` on the side it arrived from, not across, gets the take-off back, and no more
  are taken on that target (`arrive_check`: 3 of the 896 corners reached that were missed,
  none lost);
- creeping across: a joint that creeps across its goal, slow, on about the actor's hold
  (`creep_hold`, 5 % of the limit) is one friction does not hold (the twin's soft friction
  lets a 0.3-0.7 N m joint drift 1-2 mrad/s for 15 s on a command within 17 mA of its
  hold). Its stuck ramp then runs at `creep_rate` (half): at the full rate, seen breaking
  away periods late on a noisy sensor, it kicked such joints 40 mrad back through their goal
  in the last second. Pushed across by what is left of a ramp (70-110 mA past the hold) a
  joint says nothing of its friction, and ramps back at the full rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from policy.controllers.settle_law import SettleLaw
from protocol.alpha5 import JOINT_LETTERS, N_JOINTS

# Time constant of the noise estimates (s): 20 samples at 20 Hz, a spread known to +-20 %.
NOISE_FILTER_S = 1.0
# ... and the weight (of 1) an estimate has gathered from its start at 0 before it is trusted
NOISE_SETTLED = 0.8


@dataclass
class SettleSupervisor:
    """The per-joint state machine: `update` each control step with the actor's command."""

    law: SettleLaw
    limits_mA: np.ndarray
    engaged: np.ndarray = field(init=False)
    reasons: list[str] = field(init=False)

    def __post_init__(self) -> None:
        self.limits_mA = np.asarray(self.limits_mA, dtype=float)
        watched = self.law.prompt_joints if self.law.crossing_on_prompt_loop else ""
        self._prompt_watch = np.array([letter in watched for letter in JOINT_LETTERS])
        self._reverse_watch = np.array([x in self.law.prompt_joints for x in JOINT_LETTERS])
        self.reset()

    def reset(self) -> None:
        n = N_JOINTS
        self.engaged = np.zeros(n, dtype=bool)
        self.reasons = [""] * n
        self.engaged_at = np.full(n, math.nan)
        self.releases = np.zeros(n, dtype=int)
        self._target: np.ndarray | None = None
        self._t: float | None = None
        self._u_goal: np.ndarray | None = None
        self._fresh = np.ones(n, dtype=bool)
        self.e_f = np.zeros(n)
        self.v_f = np.zeros(n)
        self.u_f = np.zeros(n)
        self.u_i = np.zeros(n)
        self._sign = np.zeros(n)
        self._rev_start = np.full(n, math.nan)
        self._rev_last = np.full(n, math.nan)
        self._rev_count = np.zeros(n, dtype=int)
        self._stuck_for = np.zeros(n)
        self._stuck_e0 = np.zeros(n)  # abs(e_f) when the stuck watch's timer began
        self._held_for = np.zeros(n)
        self._in_band_for = np.zeros(n)
        window = max(1, int(round(self.law.jitter_window_s / self.law.default_dt)))
        self._v2 = np.zeros((window, n))
        self._v2_n = 0
        self._ramped = np.zeros(n)
        self._was_stuck = np.zeros(n, dtype=bool)
        self._stuck_from = np.zeros(n)
        self._ramp_side = np.zeros(n)
        self._ramp_scale = np.ones(n)
        self._e_prev = np.zeros(n)
        self._arriving = np.zeros(n, dtype=bool)
        self._side = np.zeros(n)  # the side of the goal the low-passed error was last on,
        # outside `freeze`
        self._since_break = np.full(n, math.inf)
        self._jump_from = np.full(n, math.nan)  # u_i before a jump to the hold, while checked
        self._jump_age = np.zeros(n)
        self._jump_to = np.zeros(n)
        self._hold_bad = np.zeros(n, dtype=bool)
        self._arrive_scale = np.ones(n)  # of `arrive`: shrinks by `arrive_decay` per push
        self._away_peak = np.zeros(n)  # fastest low-passed speed away from the goal, this move
        self._fall_side = np.zeros(n)  # the side of the goal the joint last fell on
        self._fall_scale = np.ones(n)  # of `fall_ramp`: shrinks by `fall_decay` per side
        self._took = np.zeros(n)  # what the last arrival took off, until the joint crosses
        self._arrive_off = np.zeros(n, dtype=bool)  # an arrival's take-off did not hold it
        self._coast_side = np.zeros(n)  # the side of the goal it was engaged on (0: unwatched)
        self._engaged_for = np.zeros(n)  # s since it was engaged
        self._crept = np.zeros(n, dtype=bool)  # crept across its goal on the hold (`creep_rate`)
        self._rate = np.ones(n)  # the ramp's rate: 1, or memory_rate when restarted from memory
        self._break_u = np.full((n, 2), math.nan)  # per side: the command it last broke away at
        # a breakaway until `restick_s` later (`confirm_breakaway`): the ramp it ended (its
        # backoff was `backoff` of that) and the memory it replaced
        self._brk_pending = np.zeros(n, dtype=bool)
        self._brk_ramped = np.zeros(n)
        self._brk_prev = np.full(n, math.nan)
        self._q_var = np.zeros(n)  # the sensors' noise, from successive samples while slow
        self._v_var = np.zeros(n)
        self._v_w = np.zeros(n)  # the weight the speed-noise EMA has gathered (from 0 at reset)
        self._q_hist = np.full((2, n), math.nan)
        self._v_prev = np.full(n, math.nan)
        self._step = 0
        self._clock = 0.0
        self._onset: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._samples: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.latency_periods: float | None = None
        self._timed = False
        self._period = self.law.default_dt

    def report(self) -> dict[str, Any]:
        """What the supervisor did on the current target: the latency it timed (periods, None
        before it has) and each joint it engaged, why, when (the controller's clock, s) and
        how often it was released back to the actor."""
        engaged = {
            JOINT_LETTERS[j]: {
                "reason": self.reasons[j],
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
        periods, timed, period = self.latency_periods, self._timed, self._period
        self.reset()
        if timed:
            self.latency_periods, self._timed, self._period = periods, True, period
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
        self.e_f = np.where(self._fresh, e, self.e_f + a * (e - self.e_f))
        self.v_f = np.where(self._fresh, qdot, self.v_f + a * (qdot - self.v_f))
        b = min(1.0, dt / law.hold_filter_s)
        self.u_f = np.where(self._fresh, u, self.u_f + b * (u - self.u_f))
        self._fresh[:] = False
        v_last = self._v_prev.copy()
        self._estimate_noise(dt, e, qdot)
        near = np.abs(e) < law.band
        self._v2[self._v2_n % self._v2.shape[0]] = qdot**2
        self._v2_n += 1
        self._u_goal = u_goal
        latent = law.latent_crossing_speed > 0 and law.crossing_speed > 0
        if latent and self.latency_periods is None:
            self._time_latency(dt, q, qdot, e, u)
        crossing_speed = np.full(N_JOINTS, law.crossing_speed)
        ahead = -1.0
        if latent and (self.latency_periods or 0.0) >= law.latent_periods:
            crossing_speed[:] = law.latent_crossing_speed
            if law.latent_ahead >= 0:
                ahead = ((self.latency_periods or 0.0) + law.latent_ahead) * self._period
        elif latent and self._timed:
            # timed without latency: an overshoot is the actor's own, but on those joints
            crossing_speed[~self._prompt_watch] = 0.0
        out = np.asarray(u, dtype=float).copy()
        for j in range(N_JOINTS):
            if self.engaged[j] and abs(e[j]) > law.release:
                self._release(j)
            if not self.engaged[j]:
                self._watch(j, now, dt, near[j], e[j], u[j], qdot[j])
            reversed_ = qdot[j] * v_last[j] < 0 and self._reverse_watch[j] and near[j]
            fast = min(abs(qdot[j]), abs(v_last[j])) >= law.reversing_speed > 0
            if not self.engaged[j] and reversed_ and fast:
                self._engage(j, now, "reversing")
            if not self.engaged[j] and crossing_speed[j] > 0:
                crossed = self._e_prev[j] * e[j] < 0
                if crossed and abs(qdot[j]) >= crossing_speed[j]:
                    self._engage(j, now, "crossing")
                elif ahead >= 0 and near[j] and abs(qdot[j]) >= crossing_speed[j]:
                    if (e[j] - qdot[j] * ahead) * e[j] < 0:
                        self._engage(j, now, "crossing ahead")
            self._e_prev[j] = e[j]
            if self.engaged[j]:
                out[j] = self._settle(j, dt, e[j], qdot[j])
        return out

    def _estimate_noise(self, dt: float, e: np.ndarray, qdot: np.ndarray) -> None:
        """Position and speed noise per joint from second (position) and first (speed)
        differences of successive samples while the joint is slow, where noise dominates
        them: var(e_k - 2 e_k-1 + e_k-2) = 6 var(e), var(v_k - v_k-1) = 2 var(v)."""
        slow = np.abs(self.v_f) < self.law.stuck_speed
        a = min(1.0, dt / NOISE_FILTER_S)
        dd = e - 2 * self._q_hist[1] + self._q_hist[0]
        ok = slow & np.isfinite(dd)
        self._q_var = np.where(ok, self._q_var + a * (dd**2 / 6 - self._q_var), self._q_var)
        dv = qdot - self._v_prev
        ok = slow & np.isfinite(dv)
        self._v_var = np.where(ok, self._v_var + a * (dv**2 / 2 - self._v_var), self._v_var)
        self._v_w = np.where(ok, self._v_w + a * (1.0 - self._v_w), self._v_w)
        self._q_hist = np.stack([self._q_hist[1], e.astype(float)])
        self._v_prev = np.asarray(qdot, dtype=float).copy()

    def _time_latency(
        self, dt: float, q: np.ndarray, qdot: np.ndarray, e: np.ndarray, u: np.ndarray
    ) -> None:
        """`latency_periods` from a target's first samples (module docstring, "Latency")."""
        law = self.law
        self._step += 1
        if self._onset is None:
            hard = (
                (np.abs(u) >= law.onset_fraction * self.limits_mA)
                & (np.abs(e) >= law.onset_error)
                & (np.sign(u) == np.sign(e))
            )
            self._onset = (hard, np.sign(u) * hard, q.copy())
            if not hard.any():
                self.latency_periods = 0.0  # nothing to time it by; the next target tries
            return
        self._clock += dt
        hard, sign, q0 = self._onset
        self._samples.append((self._clock, sign * (q - q0), sign * qdot))
        if self._step < law.onset_steps:
            return
        starts: list[float] = []
        times = np.array([s[0] for s in self._samples])
        for j in np.flatnonzero(hard):
            moved = np.array([s[1][j] for s in self._samples])
            speed = np.array([s[2][j] for s in self._samples])
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
        self._period = period
        self.latency_periods = max(0.0, min(starts)) / period if starts else 0.0
        self._timed = bool(starts)

    def _watch(
        self, j: int, now: float, dt: float, near: bool, e: float, u: float, qdot: float
    ) -> None:
        law = self.law
        if law.stuck and not near and abs(e) < law.stuck_band:
            self._watch_stuck(j, now, dt, qdot)
            return
        if not near:
            self._sign[j] = 0.0
            self._rev_count[j] = 0
            self._stuck_for[j] = 0.0
            self._held_for[j] = 0.0
            self._in_band_for[j] = 0.0
            return
        if law.cycles and abs(u) >= law.reversal_fraction * self.limits_mA[j]:
            sign = math.copysign(1.0, u)
            if self._sign[j] != 0.0 and sign != self._sign[j]:
                if not now - self._rev_last[j] <= law.max_gap_s:
                    self._rev_start[j], self._rev_count[j] = now, 0
                self._rev_last[j] = now
                self._rev_count[j] += 1
                span = now - self._rev_start[j]
                if self._rev_count[j] >= law.reversals and span >= law.min_span_s - 1e-9:
                    self._engage(j, now, "cycling")
                    return
            self._sign[j] = sign
        if law.jitter_speed > 0:
            inside = abs(e if law.jitter_raw else self.e_f[j]) < law.jitter_band
            self._in_band_for[j] = self._in_band_for[j] + dt if inside else 0.0
            if self._in_band_for[j] >= law.jitter_s - 1e-9 and self._v2_n >= self._v2.shape[0]:
                rms = math.sqrt(float(np.mean(self._v2[:, j])))
                if rms > self._jitter_limit():
                    self._engage(j, now, "jitter")
                    return
        if law.hold_s > 0:
            settled = abs(self.e_f[j]) < law.hold_error
            self._held_for[j] = self._held_for[j] + dt if settled else 0.0
            if self._held_for[j] >= law.hold_s - 1e-9:
                self._engage(j, now, "hold")
                return
        if law.stuck:
            self._watch_stuck(j, now, dt, qdot)

    def _jitter_limit(self) -> float:
        """The jitter watch's threshold: `jitter_speed`, or lower on a quiet arm, where true
        speed of `jitter_true_speed` shows over the noise (`jitter_noise_k` sigma of it). The
        noise is the arm's sensors', so the quietest joint whose estimate has settled (80 %
        of its weight: 1.6 s of slow samples) gives it; a dithering joint's own is inflated."""
        law = self.law
        settled = self._v_w >= NOISE_SETTLED
        if law.jitter_true_speed <= 0 or not settled.any():
            return law.jitter_speed
        sigma = math.sqrt(float(np.min(self._v_var[settled] / self._v_w[settled])))
        return min(law.jitter_speed, math.hypot(law.jitter_true_speed, law.jitter_noise_k * sigma))

    def _noise_floors(self, j: int, dt: float) -> tuple[float, float]:
        """What the sensors' noise can explain, `noise_sigmas` of it: of the low-passed speed
        and of a change in the low-passed error (an EMA of gain a keeps a / (2 - a) of its
        samples' variance; a difference of two of them, twice that)."""
        a = min(1.0, dt / self.law.filter_s)
        shrink = a / (2 - a)
        speed = self.law.noise_sigmas * math.sqrt(shrink * self._v_var[j])
        moved = self.law.noise_sigmas * math.sqrt(2 * shrink * self._q_var[j])
        return speed, moved

    def _slipping(self, j: int, e: float, qdot: float) -> bool:
        """One sample's measured speed towards the goal beyond what the noise explains."""
        law = self.law
        floor = max(2 * law.stuck_speed, law.noise_sigmas * math.sqrt(self._v_var[j]))
        return math.copysign(1.0, e) * qdot >= floor

    def _watch_stuck(self, j: int, now: float, dt: float, qdot: float) -> None:
        law = self.law
        slow = abs(self.v_f[j]) < max(law.stuck_speed, self._noise_floors(j, dt)[0])
        if slow and law.raw_breakaway:  # not a joint that has just begun to slip
            slow = not self._slipping(j, self.e_f[j], qdot)
        still = abs(self.e_f[j]) > law.stuck_error and slow
        if still and self._stuck_for[j] > 0 and law.creep_arrive_s > 0:
            # creeping in slower than the noisy speed can show: the low-passed error has
            # shrunk since the watch began by more than the noise explains, fast enough to
            # arrive within `creep_arrive_s` (a slower creep is as good as stuck)
            shrunk = self._stuck_e0[j] - abs(self.e_f[j])
            moved = max(law.progress, self._noise_floors(j, dt)[1])
            soon = abs(self.e_f[j]) * self._stuck_for[j] / law.creep_arrive_s
            if shrunk > moved and shrunk >= soon:
                still = False
        if still and self._stuck_for[j] == 0:
            self._stuck_e0[j] = abs(self.e_f[j])
        self._stuck_for[j] = self._stuck_for[j] + dt if still else 0.0
        if self._stuck_for[j] >= law.stuck_s - 1e-9:
            self._engage(j, now, "stuck")

    def _engage(self, j: int, now: float, why: str) -> None:
        self.engaged[j] = True
        self.reasons[j] = why
        self.engaged_at[j] = now
        # The actor's hold on the goal; but a joint stuck short is at rest under the actor's
        # steady command, which holds it there (on a weak joint, several times the nominal
        # hold), so it starts from that low-passed command, as does a supervisor used without
        # an actor (u_goal not given).
        if self._u_goal is None or why == "stuck":
            self.u_i[j] = self.u_f[j]
        elif why == "jitter":
            self._to_hold(j, float(self._u_goal[j]), self.u_f[j])
        elif not (self.law.fall_memory and self._hold_bad[j]):
            self.u_i[j] = float(self._u_goal[j])
        self._ramped[j] = 0.0
        self._was_stuck[j] = False
        self._brk_pending[j] = False  # a breakaway before a release is not this engagement's
        self._crept[j] = False
        # a joint stuck short is at rest, not coasting: only the others are watched (`coast_s`)
        self._coast_side[j] = 0.0 if why == "stuck" else math.copysign(1.0, self.e_f[j])
        self._engaged_for[j] = 0.0

    def _to_hold(self, j: int, hold: float, alt: float) -> None:
        """u_i to the actor's hold, checked (`hold_check`) against `alt`, what held it so far."""
        if self._hold_bad[j]:
            self.u_i[j] = alt
            return
        self.u_i[j] = hold
        if abs(hold - alt) < self.law.creep_hold * self.limits_mA[j]:
            return  # about the same: nothing to check
        self._jump_from[j] = alt
        self._jump_to[j] = hold
        self._jump_age[j] = 0.0

    def _release(self, j: int) -> None:
        self.engaged[j] = False
        self.releases[j] += 1
        self._sign[j] = 0.0
        self._rev_count[j] = 0
        self._rev_last[j] = math.nan
        self._stuck_for[j] = 0.0

    def _fall(self, j: int, dt: float, ef: float, floor: float) -> None:
        """`fall_ramp`: a joint outside `band` moving away from its goal at the fastest it has
        since it began to (within `floor`), not slowing as a coast through the goal does, is
        falling: what it is on does not hold it."""
        law = self.law
        away = -math.copysign(1.0, ef) * self.v_f[j]
        self._away_peak[j] = 0.0 if away < floor else max(self._away_peak[j], away)
        if abs(ef) <= law.band or away < floor or away < self._away_peak[j] - floor:
            return
        side = math.copysign(1.0, ef)
        if self._fall_side[j] == -side:  # the last fall's ramp carried it through its goal
            self._fall_scale[j] *= law.fall_decay
        self._fall_side[j] = side
        self._hold_bad[j] = True
        rate = law.fall_ramp * self._fall_scale[j] * law.ramp[j] * self.limits_mA[j]
        self.u_i[j] += side * rate * dt

    def _coast(self, j: int, ef: float, floor: float) -> None:
        """`coast_s`: a joint still moving away from its goal that long after its engagement,
        that far past it, is one on which the soft gains act as a fraction of themselves. The
        watch ends there, or once the joint is seen coming back after `coast_s`."""
        law = self.law
        if self._engaged_for[j] < law.coast_s - 1e-9:
            return
        past = -self._coast_side[j] * ef  # > 0: on the far side of the goal
        away = -math.copysign(1.0, ef) * self.v_f[j]
        if past > law.coast_band and away >= floor:
            self._hold_bad[j] = True
            self._coast_side[j] = 0.0
        elif away <= -floor:
            self._coast_side[j] = 0.0

    def _confirm(self, j: int, ef: float, slow: bool, progress: float) -> None:
        """`restick_s` after a breakaway: a joint that is slow and further from its goal than
        where its ramp began, by more than the noise explains (`progress`), did not break
        away; noise said it did. Its backoff is given back and its ramp goes on where it
        stood."""
        away = self._ramp_side[j] * ef - self._stuck_from[j]  # < 0: nearer, or through
        if away > progress and slow and not self._was_stuck[j]:
            k = 0 if self._ramp_side[j] > 0 else 1
            self.u_i[j] += self.law.backoff * self._brk_ramped[j]
            self._ramped[j] = self._brk_ramped[j]
            self._break_u[j, k] = self._brk_prev[j]
            self._was_stuck[j] = True
        self._brk_pending[j] = False

    def _settle(self, j: int, dt: float, e: float, qdot: float) -> float:
        law = self.law
        limit = self.limits_mA[j]
        ef = self.e_f[j]
        if abs(ef) > law.freeze or abs(self.v_f[j]) >= law.stuck_speed:
            gain = law.fall_gain if self._hold_bad[j] else 1.0
            self.u_i[j] += gain * law.ki[j] * e * dt
        may_ramp = law.stuck if self.reasons[j] == "stuck" else law.ramp_engaged
        speed_floor, moved_floor = self._noise_floors(j, dt)
        moving = max(law.stuck_speed, speed_floor)  # a low-passed speed beyond the noise
        slow = abs(self.v_f[j]) < moving
        # Breakaway: the low-passed speed, or (`progress` > 0) the low-passed error having
        # shrunk by `progress` since the ramp began; a joint creeping in slower than the noisy
        # speed can show has broken away too, and ramping on would carry it through its goal.
        progress = max(law.progress, moved_floor)
        moved = law.progress > 0 and abs(ef) < self._stuck_from[j] - progress
        toward = math.copysign(1.0, ef) * self.v_f[j]  # > 0: moving towards the goal
        broke = toward >= moving or moved
        if law.raw_breakaway and not broke:
            broke = self._slipping(j, ef, qdot)
        if law.freeze_breakaway and abs(ef) <= law.freeze:
            # ramped in from outside `stuck_error` to inside `freeze`: it broke away, though
            # on a noisy sensor `progress` may not have said so yet
            broke = True
        self._since_break[j] += dt
        if law.hold_check and math.isfinite(self._jump_from[j]):
            self._jump_age[j] += dt
            window = ((self.latency_periods or 0.0) + 4.0) * self._period
            d = math.copysign(1.0, self._jump_to[j] - self._jump_from[j])
            if d * self.v_f[j] >= moving and d * qdot >= moving:
                self.u_i[j] += self._jump_from[j] - self._jump_to[j]
                self._hold_bad[j] = True
                self._jump_from[j] = math.nan
            elif self._jump_age[j] > window + 1e-9:
                self._jump_from[j] = math.nan
        if law.fall_ramp > 0:
            self._fall(j, dt, ef, moving)
        self._engaged_for[j] += dt
        if law.coast_s > 0 and self._coast_side[j] != 0:
            self._coast(j, ef, moving)
        if self._brk_pending[j] and self._since_break[j] >= law.restick_s - 1e-9:
            self._confirm(j, ef, slow, progress)
        if self._was_stuck[j] and broke:
            self._since_break[j] = 0.0
            k = 0 if self._ramp_side[j] > 0 else 1
            if law.confirm_breakaway and abs(ef) > law.freeze:
                self._brk_pending[j] = True
                self._brk_ramped[j] = self._ramped[j]
                self._brk_prev[j] = self._break_u[j, k]
            self._break_u[j, k] = self.u_i[j]
            self.u_i[j] -= law.backoff * self._ramped[j]
            self._ramped[j] = 0.0
            self._was_stuck[j] = False
        elif (
            may_ramp
            and abs(ef) > law.stuck_error
            and slow
            and self._since_break[j] >= law.restick_s - 1e-9
        ):
            if not self._was_stuck[j]:
                self._stuck_from[j] = abs(ef)
                side = math.copysign(1.0, ef)
                if self._ramp_side[j] == -side:  # the last breakaway carried it through
                    self._ramp_scale[j] = max(law.ramp_floor, law.ramp_decay * self._ramp_scale[j])
                self._ramp_side[j] = side
                brk = self._break_u[j, 0 if side > 0 else 1]
                self._rate[j] = law.creep_rate if self._crept[j] else 1.0
                hold = None if self._u_goal is None else float(self._u_goal[j])
                other = self._break_u[j, 1 if side > 0 else 0]  # broke away the other way at
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
                        self._ramped[j] += jump
                        self._rate[j] = law.memory_rate
            rate = law.ramp[j] * self._ramp_scale[j] * self._rate[j]
            if law.ramp_grow[j] > 0:
                rate *= 1.0 + abs(self._ramped[j]) / (law.ramp_grow[j] * limit)
            step = math.copysign(rate * limit * dt, ef)
            self.u_i[j] += step
            self._ramped[j] += step
            self._was_stuck[j] = True
        if abs(ef) <= law.freeze:
            self._ramped[j] = 0.0
            self._was_stuck[j] = False
        # An arrival is armed outside twice `stuck_error` and spent once the joint is inside
        # `stuck_error`: taken off if it creeps in, or left alone if it comes to rest there.
        # Only on a joint engaged because it was stuck: friction holds it, not its command.
        if law.arrive > 0 and self.reasons[j] == "stuck" and abs(ef) > 2 * law.stuck_error:
            if law.arrive_check and self._took[j] != 0 and self._took[j] * ef > 0:
                # back out on the side it arrived from, not across: what was taken off held it
                self.u_i[j] += self._took[j]
                self._took[j] = 0.0
                self._arrive_off[j] = True
            self._arriving[j] = not self._arrive_off[j]
        elif self._arriving[j] and abs(ef) < law.stuck_error:
            if toward > max(0.5 * law.stuck_speed, speed_floor):
                took = math.copysign(law.arrive * limit * self._arrive_scale[j], ef)
                self.u_i[j] -= took
                self._took[j] = took
                self._arriving[j] = False
            elif slow:
                self._arriving[j] = False
        if abs(ef) > law.freeze:
            side = math.copysign(1.0, ef)
            if self._side[j] == -side:  # crossed its goal since it was last outside `freeze`
                self._took[j] = 0.0
                hold = None if self._u_goal is None else float(self._u_goal[j])
                if slow and hold is not None and abs(self.u_i[j] - hold) < law.creep_hold * limit:
                    # crept across on about the actor's hold, no ramp pushing it: friction is weak
                    self._crept[j] = True
                if law.arrive > 0 and self.reasons[j] == "stuck":
                    # crept across the goal (not ramping: a ramp's breakaway has its backoff)
                    self.u_i[j] += side * law.arrive * limit * self._arrive_scale[j]
                    self._arrive_scale[j] *= law.arrive_decay
            self._side[j] = side
        self.u_i[j] = float(np.clip(self.u_i[j], -limit, limit))
        gain = law.fall_gain if self._hold_bad[j] else 1.0
        cmd = self.u_i[j] + gain * (law.kp[j] * e - law.kd[j] * qdot)
        return float(np.clip(cmd, -limit, limit))
