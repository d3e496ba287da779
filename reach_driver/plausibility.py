"""Is a state the arm reported physically possible? Checked before any controller sees it.

A glitching encoder or a corrupted-but-valid frame can report an angle no joint can have
(1e6 rad, -1 rad) or one it cannot have reached since the last sample (6.2 rad a period
after 3.5 rad). Taken as truth, one such sample kicks a controller (a learned one most),
so each joint's sample must lie inside the arm's physical envelope (the factory position
limits with `envelope_margin`), must not have moved further since the joint's last good
sample than `MAX_JOINT_SPEED` x the elapsed arm time + `jump_margin` (the sensor noise),
and its velocity must not exceed that speed + `speed_margin`.

A velocity can also be wrong while it looks fine: a sensor or firmware stuck at one value
keeps sending it, well formed and on time. An arm at rest may report one value for a long
time, so a repeated value alone proves nothing; what no joint can do is move otherwise than
the velocity it reports. While a joint's velocity comes in exactly equal, fresh report after
fresh report, its position must have moved by that velocity x the arm time since, within
`stuck_margin` (over the last `stuck_window_s` at most, so a coarse velocity at a slow creep
is not judged over minutes): a velocity frozen at 0 while the joint moves 0.5 rad/s fails
within a tick, one frozen at 0.8 rad/s once the joint has stopped likewise. A value found
stuck stays implausible until the velocity changes (it may agree with the motion now and
then: a joint moving at the speed it froze at), so a stuck sensor ends the run.

After a gap in the stream (ticks lost whole, which the loop's arm time does not count) the
arm time between two samples is only known from below: the caller passes its estimate of the
time that passed unseen (`unseen_s`), the jump allowed grows by it, and a repeated velocity is
judged afresh from the first sample after the gap.

A joint whose sample fails keeps its last good position and velocity for that tick (held,
not extrapolated); the control loop counts it, reports it, and stops the run when a joint
stays implausible for as long as feedback may be stale.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from protocol.alpha5 import FACTORY_POSITION_LIMITS, JOINTS, MAX_JOINT_SPEED

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class PlausibilityConfig:
    """Margins of the feedback check (rad, rad/s): noise and calibration slack."""

    envelope_margin: float = 0.1
    jump_margin: float = 0.05
    speed_margin: float = 0.5
    #: rad: how far a joint may move otherwise than an unchanging velocity says (10 x the
    #: virtual arm's 0.002 rad position noise; one lost velocity packet held for a tick while
    #: accelerating stays well inside it, and held values are not judged)
    stuck_margin: float = 0.02
    #: s of arm time a repeated velocity is judged over at most
    stuck_window_s: float = 0.5


@dataclass(frozen=True)
class Verdict:
    """One tick's check: which joints' samples are implausible, and why (per joint)."""

    bad: np.ndarray  # bool per joint, E D C B
    why: tuple[str, ...]  # "E: position 1e+06 rad outside [-0.0825, 6.243]", ...


class FeedbackCheck:
    """Checks each tick's joint states against the envelope, the top speed and the last good
    sample (arm time), and gives the state a controller may see."""

    def __init__(self, config: PlausibilityConfig | None = None) -> None:
        self.config = cfg = config or PlausibilityConfig()
        self.lo = np.array([FACTORY_POSITION_LIMITS[d][0] for d in JOINTS]) - cfg.envelope_margin
        self.hi = np.array([FACTORY_POSITION_LIMITS[d][1] for d in JOINTS]) + cfg.envelope_margin
        # A joint whose envelope is a whole turn may wrap (0 and 2 pi are one angle).
        self.wraps = np.array(
            [
                FACTORY_POSITION_LIMITS[d][1] - FACTORY_POSITION_LIMITS[d][0] >= TWO_PI - 1e-6
                for d in JOINTS
            ]
        )
        self.top = np.asarray(MAX_JOINT_SPEED, dtype=float)
        self.good_q = np.full(len(JOINTS), np.nan)
        self.good_qdot = np.full(len(JOINTS), np.nan)
        self.good_t = np.full(len(JOINTS), np.nan)
        self.unseen = np.zeros(len(JOINTS))  # arm time passed unseen since the good sample
        # per joint, while its fresh velocity repeats exactly: that value and the (arm time,
        # position) of each sample since it first came, the oldest kept within the window
        self.same_v = np.full(len(JOINTS), np.nan)
        self.same_since: list[deque[tuple[float, float]]] = [deque() for _ in JOINTS]
        self.stuck: list[tuple[float, str] | None] = [None for _ in JOINTS]  # (value, why)

    def check(
        self,
        t: float,
        q: np.ndarray,
        qdot: np.ndarray,
        fresh: np.ndarray | None = None,
        unseen_s: float = 0.0,
    ) -> Verdict:
        """Judge the sample at arm time `t`; plausible joints the arm reported in it become
        the new good ones.
        `fresh` says per joint whether its velocity was reported for this sample (a value
        held over a lost packet repeats without being a repeat; default: all fresh);
        `unseen_s`: arm time that may have passed since the last sample on top of what `t`
        counts (ticks lost whole in a gap of the stream)."""
        cfg = self.config
        if unseen_s > 0.0:
            self.unseen += unseen_s
            for since in self.same_since:
                since.clear()
        jump = np.abs(q - self.good_q)
        jump = np.where(self.wraps, np.minimum(jump, TWO_PI - jump), jump)
        allowed = self.top * (t - self.good_t + self.unseen) + cfg.jump_margin
        why: list[str] = []
        bad = np.zeros(len(JOINTS), dtype=bool)
        for i, dev in enumerate(JOINTS):
            name = dev.name
            if not self.lo[i] <= q[i] <= self.hi[i]:
                why.append(
                    f"{name}: position {q[i]:.6g} rad outside [{self.lo[i]:.4g}, {self.hi[i]:.4g}]"
                )
            elif abs(qdot[i]) > self.top[i] + cfg.speed_margin:
                why.append(
                    f"{name}: velocity {qdot[i]:.6g} rad/s beyond "
                    f"{self.top[i] + cfg.speed_margin:g}"
                )
            elif np.isfinite(self.good_t[i]) and jump[i] > allowed[i]:
                why.append(
                    f"{name}: position {q[i]:.6g} rad, {jump[i]:.4g} rad from "
                    f"{self.good_q[i]:.6g} in {t - self.good_t[i] + self.unseen[i]:.3g} s "
                    f"(at most {allowed[i]:.3g})"
                )
            elif stuck := self._stuck(i, t, q[i], qdot[i], fresh is None or bool(fresh[i])):
                why.append(f"{name}: {stuck}")
            else:
                continue
            bad[i] = True
        # the reference for the next jump: a sample the arm reported (not one filled in)
        ok = ~bad if fresh is None else ~bad & fresh
        self.good_q[ok], self.good_qdot[ok], self.good_t[ok] = q[ok], qdot[ok], t
        self.unseen[ok] = 0.0
        return Verdict(bad, tuple(why))

    def _stuck(self, i: int, t: float, q: float, v: float, fresh: bool) -> str | None:
        """Whether joint i's velocity `v` is stuck (why, if so): the value found stuck before,
        or, fresh and the same as its last fresh ones, one that disagrees with how far the
        joint moved meanwhile. A new value starts a new run."""
        stuck = self.stuck[i]
        if stuck is not None:
            if v == stuck[0]:
                return stuck[1]
            if fresh:
                self.stuck[i] = None
        if not fresh:
            return None
        since = self.same_since[i]
        if v != self.same_v[i] or not since:
            self.same_v[i] = v
            since.clear()
            since.append((t, q))
            return None
        cfg = self.config
        while len(since) > 1 and since[1][0] <= t - cfg.stuck_window_s:
            since.popleft()
        since.append((t, q))
        t0, q0 = since[0]
        moved = q - q0
        if self.wraps[i]:
            moved = (moved + math.pi) % TWO_PI - math.pi
        expected = v * (t - t0)
        if abs(moved - expected) <= cfg.stuck_margin:
            return None
        why = (
            f"velocity stuck at {v:.6g} rad/s (over {t - t0:.3g} s to t = {t:.2f} s the "
            f"position moved {moved:.4g} rad, that velocity moves it {expected:.4g} rad)"
        )
        self.stuck[i] = (v, why)
        return why

    def held(
        self, q: np.ndarray, qdot: np.ndarray, verdict: Verdict
    ) -> tuple[np.ndarray, np.ndarray]:
        """The state a controller sees: each implausible joint at its last good sample."""
        return (
            np.where(verdict.bad, self.good_q, q),
            np.where(verdict.bad, self.good_qdot, qdot),
        )

    @property
    def has_good(self) -> bool:
        """Whether every joint has had a good sample (else nothing can be held)."""
        return bool(np.all(np.isfinite(self.good_t)))
