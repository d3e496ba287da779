"""Is the arm streaming at the rate the loop asked for? Measured from the arm's own data.

The streaming loop counts arm time in heartbeat ticks at the rate it asked for. An arm that
streams at another rate (half: each tick spans two periods; double: half a period) would make
the run's duration, the controller's time step and every metric silently wrong. BPL packets
carry no arm timestamp, and host arrival times cannot tell a fast arm from `reach-sim
--speed X`, so the rate is measured from the arm's kinematics: between two ticks a joint moves
by its velocity x the true elapsed time. Over the samples where a joint moves clearly
(|velocity| >= `min_speed`, well above sensor noise) and not starting hard (its speed at
the start at least `min_start_share` of its speed at the end), the least-squares ratio of
the position change to velocity x the asked period is the true tick period over the asked
one. Once the motion seen adds up to `min_travel` rad, a ratio off 1 by more than
`tolerance` is judged.

Only what the arm really reported between two consecutive ticks measures it. An interval is
left out for a joint whose sample at either end was not reported in its tick (a lost packet
filled in by the state assembler: an extrapolated position moves by exactly velocity x
period, whatever the rate) or was implausible (held at its last good sample: it moved 0 while
its held velocity says otherwise), whose velocity came in exactly the same at both ends (a
velocity stuck at one value, `reach_driver.plausibility`, says nothing of the time between),
and for every joint across a gap in the stream (`resumed`: ticks lost whole, which the loop
does not count, as when the stream went to another UDP client for a while).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RateConfig:
    tolerance: float = 0.25  # |measured / asked - 1| allowed (half and double are 0.5 and 1)
    min_speed: float = 0.1  # rad/s: slower samples say little beside the velocity noise
    min_travel: float = 0.1  # rad of expected motion before the ratio is judged
    min_start_share: float = 0.5  # an interval's first speed, as a share of its last, at least


class RateCheck:
    """Accumulates (position change, velocity x asked time) over consecutive ticks."""

    def __init__(self, asked_hz: float, config: RateConfig | None = None) -> None:
        self.asked_hz = asked_hz
        self.config = config or RateConfig()
        self.prev: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.sxy = 0.0
        self.sxx = 0.0
        self.travel = 0.0

    def update(
        self,
        ticks: int,
        q: np.ndarray,
        qdot: np.ndarray,
        ok: np.ndarray | None = None,
        resumed: bool = False,
    ) -> None:
        """Add the sample of heartbeat tick `ticks`; `ok` per joint: reported in this tick and
        plausible (default all); `resumed`: ticks were lost whole since the last sample."""
        ok = np.ones(len(q), dtype=bool) if ok is None else np.asarray(ok, dtype=bool)
        prev, self.prev = self.prev, (ticks, q.copy(), qdot.copy(), ok.copy())
        if prev is None or ticks <= prev[0] or resumed:
            return
        n0, q0, v0, ok0 = prev
        v = 0.5 * (v0 + qdot)
        x = v * (ticks - n0) / self.asked_hz  # the motion if a tick is the asked period
        dq = q - q0
        dq = (dq + math.pi) % (2 * math.pi) - math.pi  # a wrapping joint: the short way
        use = (np.abs(v0) >= self.config.min_speed) & (np.abs(qdot) >= self.config.min_speed)
        use &= np.sign(v0) == np.sign(qdot)  # no reversal inside the interval
        use &= ok0 & ok & (v0 != qdot)  # reported, plausible, and not one repeated value
        # a joint starting hard (its speed more than doubled within the interval, as a light
        # joint reaching its top speed within a tick does) moves by more than the mean of its
        # two velocity samples: up to twice as much, which read as a stream 35 % slow
        use &= np.abs(v0) >= self.config.min_start_share * np.abs(qdot)
        self.sxy += float(np.sum(dq[use] * x[use]))
        self.sxx += float(np.sum(x[use] ** 2))
        self.travel += float(np.sum(np.abs(x[use])))

    @property
    def ratio(self) -> float | None:
        """True tick period / asked period, once enough motion was seen (else None)."""
        if self.travel < self.config.min_travel or self.sxx <= 0:
            return None
        return self.sxy / self.sxx

    @property
    def measured_hz(self) -> float | None:
        r = self.ratio
        return None if r is None or r <= 0 else self.asked_hz / r

    def off(self) -> bool:
        """Whether the measured rate is off the asked one by more than the tolerance."""
        r = self.ratio
        return r is not None and not abs(r - 1.0) <= self.config.tolerance
