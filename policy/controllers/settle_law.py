"""The settle supervisor's thresholds and gains (`SettleLaw`), each default with what set it.

What the supervisor watches, when it engages, what it commands and when it releases is in
`policy.controllers.settle`'s module docstring; this module holds the numbers, grouped by the
watch or the part of the law they set, so that a variant of the law is one dict of field
overrides (`SettleLaw.from_param`, `--param settle={...}`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from protocol.alpha5 import JOINT_LETTERS, N_JOINTS


def _four(value: Any) -> tuple[float, float, float, float]:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(N_JOINTS, float(arr))
    if arr.shape != (N_JOINTS,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"settle gains need one value or 4 (E D C B), finite, >= 0: {value!r}")
    a, b, c, d = (float(x) for x in arr)
    return (a, b, c, d)


# Linear gains, from the loop kt (kp + kd s + ki / s) e^(-s tau) / (J s^2 + b s) on a grid of
# the envelope's joints (J: the MuJoCo mass matrix's diagonal over the workspace, 0.12-0.16
# kg m^2 on E D C and 0.007 on B, times armature x0.5-1.5; b: the model's damping x0.5-1.5)
# and tau 25-130 ms (half a period of hold plus 0-2 periods of latency): the largest kp with
# a phase margin of at least 35 degrees and a gain margin of at least 2 everywhere. C (low
# viscous friction) and B (tiny inertia) get half of E and D's kp. Friction only adds margin.
DEFAULT_KP = (200.0, 200.0, 100.0, 100.0)  # mA/rad
DEFAULT_KD = (20.0, 20.0, 20.0, 10.0)  # mA/(rad/s)
DEFAULT_KI = (60.0, 60.0, 30.0, 30.0)  # mA/(rad s)
# The ramp while stuck, as a fraction of the current limit per second: 150 mA/s on E D C
# (6.6 N m of Coulomb friction is 330 mA); 15 mA/s on B, whose 0.16 N m is 22 mA and whose
# 0.004-0.011 kg m^2 a fast ramp sets hunting (measured on draw 156 of seed 1).
DEFAULT_RAMP = (0.25, 0.25, 0.25, 0.05)


@dataclass(frozen=True)
class SettleLaw:
    """Thresholds of the watch and gains of the settle law (`policy.controllers.settle`'s
    docstring)."""

    # Where it looks
    band: float = 0.15  # rad: only joints this close to their goal are watched
    release: float = 0.5  # rad: an engaged joint this far from its goal goes back to the actor
    stuck_band: float = 0.5  # rad: the stuck watch looks at joints this close to their goal

    # The low-passed signals, the control period, the noise
    filter_s: float = 0.25  # time constant of the low-passed error and speed
    hold_filter_s: float = 0.5  # ... and of the low-passed actor command u_I starts from
    default_dt: float = 0.05
    noise_sigmas: float = 3.0  # >= 0: a breakaway is a move this many standard deviations of
    # its own noise (the sensors' noise, estimated while the joint is slow) or more

    # Watch: cycling
    cycles: bool = True  # watch for cycling
    reversal_fraction: float = 0.1  # of the current limit
    reversals: int = 4
    max_gap_s: float = 0.3
    min_span_s: float = 0.4

    # Watch: crossing, and the loop's latency that sets its speed
    crossing_speed: float = 0.8  # rad/s, > 0: engage a joint that crosses its goal this fast
    latent_crossing_speed: float = 0.15  # rad/s, > 0 (and crossing_speed > 0): ... this fast
    # on a loop timed at `latent_periods` of latency or more (`onset_*` below)
    latent_periods: float = 0.2  # a loop without latency times at 0.06 +- 0.05 (max 0.23 in 100)
    latent_ahead: float = 1.0  # periods (< 0: off): on a loop timed at `latent_periods` or
    # more, engage a joint that will cross its goal at `latent_crossing_speed` or faster within
    # its latency plus this many periods (the commands in flight carry it that far)
    crossing_on_prompt_loop: bool = True  # watch crossings at `crossing_speed` on a loop timed
    # below `latent_periods` too, on the joints of `prompt_joints`. Off, the actor's own
    # overshoot there is its to finish, but 8 more of the 896 corners miss (frictionless heavy
    # rotors the actor's gain cycles)
    prompt_joints: str = "EDC"  # letters: the joints that watch on a prompt loop. Not B: B on
    # Table I's seed 2120 crosses at 1.15 rad/s and settles in 0.9 s alone, 1.7 s when engaged
    onset_fraction: float = 0.5  # of the current limit: a joint commanded this hard ...
    onset_error: float = 0.4  # rad: ... this far from its goal at a target's first step
    onset_steps: int = 8  # ... times the latency from the samples of this many steps

    # Watch: reversing
    reversing_speed: float = 0.5  # rad/s, >= 0 (0: off): engage a joint of `prompt_joints`
    # inside `band` whose measured speed reverses between two samples, this fast both ways (a
    # strong frictionless joint the actor bang-bangs about its goal, full speed each way; 0.25
    # also took arrivals on Table I's arms, and the soft law parked them 3 mrad out)

    # Watch: jitter
    jitter_speed: float = 0.08  # > 0: engage a joint whose measured speed RMS over the last
    # jitter_window_s exceeds this after jitter_s inside jitter_band (noise-driven jitter)
    jitter_true_speed: float = 0.045  # rad/s, >= 0 (0: off): once the arm's speed noise is
    # estimated, the jitter watch's threshold is hypot(this, jitter_noise_k x that noise) if
    # lower than `jitter_speed`. At 1x noise (0.02 rad/s) the actor dithered frictionless
    # joints at 0.05-0.07 rad/s of true speed (the rest metric's limit is 0.05), which read
    # 0.055-0.065 through the noise, under 0.08: 6 of the 7 corners of seed 1 it missed
    jitter_noise_k: float = 1.5  # > 0: pure noise over the 10-sample window stays under
    # 1.5 sigma with a margin; with a low multiple the watch took noisy joints at rest
    jitter_band: float = 0.03  # rad
    jitter_raw: bool = True  # time `jitter_s` from the reading's error inside `jitter_band`,
    # not the low-passed one (False), which lags a fast arrival by about its speed x
    # `filter_s`: E arriving at 1.17 rad/s on corner 370 was due 0.45 s late, after the
    # actor, dithering it on 3x noise, kicked it 60 mrad through
    jitter_s: float = 1.0
    jitter_window_s: float = 0.5

    # Watch: hold
    hold_s: float = 0.0  # > 0: engage a joint settled inside hold_error for this long
    hold_error: float = 0.015  # rad, low-passed

    # Watch: stuck short
    stuck: bool = True  # watch for stuck short (engage), and ramp while stuck
    stuck_error: float = 0.017  # rad, low-passed
    stuck_speed: float = 0.03  # rad/s, low-passed
    stuck_s: float = 1.5
    creep_arrive_s: float = 4.0  # > 0: the stuck watch restarts when the low-passed error has
    # shrunk by more than the noise explains since it began, at a rate that brings the joint
    # in within this time (creeping in, not stuck); 0: off

    # The settle law: gains and integration
    kp: tuple[float, float, float, float] = DEFAULT_KP
    kd: tuple[float, float, float, float] = DEFAULT_KD
    ki: tuple[float, float, float, float] = DEFAULT_KI
    freeze: float = 0.008  # rad, low-passed: no integration for a joint at rest inside

    # The stuck ramp
    ramp_engaged: bool = True  # ramp while stuck on a joint engaged for cycling too
    ramp: tuple[float, float, float, float] = DEFAULT_RAMP  # of the limit per second, stuck
    ramp_grow: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.1)  # of the limit (0:
    # off): a stuck ramp's rate grows by its base rate for each `ramp_grow` of the limit it
    # has added since the joint stuck (a breakaway memory's restart jump counts too). B's
    # base rate is slow (a fast one set a light B hunting), and on a weak B (25 % torque) its
    # 0.16 N m of friction is 90 mA of command, six seconds of it; growing, under three
    ramp_decay: float = 0.7  # the ramp's rate is multiplied by this each time a joint sticks
    # on the other side of its goal from where it last ramped (stick-slip hunting)
    ramp_floor: float = 0.0  # ... but not below this fraction of `ramp` (at 0.3, on a
    # frictionless arm at 3x noise the ramp kicked a C through its goal at every turn to the
    # end; only frictionless corners ever decay below)
    creep_rate: float = 0.5  # (0, 1]: the stuck ramp's rate on a joint that crept across its
    # goal, slow, on about the actor's hold: friction does not hold it, and at the full rate
    # the ramp, seen breaking away periods late on a noisy sensor, kicked such a joint 40 mrad
    # back through its goal
    creep_hold: float = 0.05  # of the limit, >= 0: "about the hold". Pushed across by a
    # ramp's residue (70-110 mA past the hold) a joint says nothing of its friction, and at
    # half the rate draw 174 of seed 1 was left short

    # Breakaway from the ramp
    backoff: float = 0.8  # of the ramp added since the joint stuck, taken back at breakaway
    progress: float = 0.004  # rad, > 0: breakaway also when the low-passed error has shrunk
    # this much since the stuck ramp began (creep slower than stuck_speed)
    raw_breakaway: bool = True  # a breakaway is also one sample's measured speed towards the
    # goal of `noise_sigmas` of its noise (and twice `stuck_speed`) or more: the low-passed
    # speed sees a slip 2-3 periods late, and on a latent loop the slip carries through the goal
    freeze_breakaway: bool = True  # a ramping joint reaching `freeze` has broken away (its
    # backoff taken, the command remembered) even where noise keeps `progress` from saying so
    confirm_breakaway: bool = True  # a breakaway after which the joint, slow `restick_s`
    # later, is further from its goal than where its ramp began, by more than the noise
    # explains, was noise: its backoff is given back and the ramp goes on (a weak B creeping
    # away from its goal while its ramp caught up lost 80 % of that ramp to one sample's
    # 3-sigma speed, and was left 20 mrad out)
    restick_s: float = 0.5  # s after a breakaway before the ramp may start again: the
    # low-passed error lags a creeping joint by speed x `filter_s` (20 mrad at 0.08 rad/s)
    memory_margin: float = 0.05  # of the limit (< 0: no memory): a joint stuck again on the
    # side it broke away from restarts its ramp this far below the command it broke away at
    memory_rate: float = 0.3  # of the ramp's rate, (0, 1]: ... and ramps this much slower
    # from there (the push past breakaway, and so the step it makes, grows with the rate)
    reverse_to_hold: float = 0.25  # of the limit (0: off): a ramp that must push the other
    # way starts from the actor's hold, not from the far side of the friction band (2 x 300 mA
    # at 6 N m), where the joint broke away the first way this far from the hold or more (on
    # a joint with little friction the actor's hold, learned on the model, is a kick)

    # Arrival of a joint engaged as stuck
    arrive: float = 0.05  # of the limit, >= 0: an engaged joint creeping into `stuck_error`
    # of its goal on the command it is left at has that much taken off it, once per arrival:
    # on a command just past breakaway it would creep on through the goal and stick beyond
    arrive_decay: float = 0.5  # (0, 1]: each push back across the goal is this much smaller
    # than the last on this target: on a frictionless weak joint the 5 % is itself a kick,
    # and the pushes kept a joint hunting 30 mrad about its goal with a period of 3 s
    arrive_check: bool = True  # an arrival's take-off (`arrive`) after which the joint backs out
    # of `2 stuck_error` on the side it arrived from is given back, and no more are taken on
    # this target: on a frictionless weak joint it was what held the joint up

    # A weak or heavy joint: the actor's hold checked, falls, coasts
    hold_check: bool = True  # a joint moved to the actor's hold (`reverse_to_hold`, or
    # engaged for jitter) that then moves the way of that change within its latency plus four
    # periods was not held by it (a weak or heavy joint): the change is undone and that
    # joint's hold is not used again on this target
    fall_ramp: float = 1.0  # >= 0, of `ramp` (0: off): an engaged joint outside `band` moving
    # away from its goal and not slowing is falling (a weak or heavy joint whose command does
    # not hold it: C at 25 % torque, on a hold 68 mA short, fell 0.5 rad); its u_i ramps towards
    # the goal at this fraction of the stuck ramp's rate while it falls, and its hold is not
    # used again on this target
    fall_decay: float = 0.5  # (0, 1]: ... each time it falls on the other side of its goal from
    # the last fall (the ramp ran on for the latency and carried it through), the rate shrinks
    fall_memory: bool = True  # a joint that fell, released and engaged again on the same
    # target, keeps the u_i it had (the actor's hold let it fall, every time: C six times)
    fall_gain: float = 2.0  # >= 1: times the gains (kp, kd, ki) on a joint whose hold is marked
    # bad, a weak or heavy one: at 25 % torque the soft gains act as a quarter, and swung a C
    # through its goal with a period of 8 s. Doubled, they use up their gain margin of 2 only
    # on the envelope's lightest, strongest joint at its longest delay, which is not one the
    # actor's hold fails (measured on the corners: 9 reached that were missed, none lost)
    coast_s: float = 0.7  # s (0: off): an engaged joint still coasting away from its goal
    # this long after it was engaged, beyond `coast_band` on the far side of the goal from
    # where it was engaged, is weak or heavy for the soft gains: they are `fall_gain` times as
    # stiff on it from then on, as on a joint whose hold failed. On every second corner (seed
    # 1) no strong joint went more than 0.26 rad past, and 23 of the 25 past 0.15 rad turned
    # within 0.55 s; a weak C (25 % torque) went up to 0.5 rad past, turning after up to 5 s,
    # then swung about its goal with a period of 8 s, kicked on by the stuck ramp at each turn
    coast_band: float = 0.2  # rad: past 0.15 it also took a strong, light D (0.17 rad)

    def __post_init__(self) -> None:
        for name in ("kp", "kd", "ki", "ramp", "ramp_grow"):
            object.__setattr__(self, name, _four(getattr(self, name)))
        positive = (
            "band",
            "release",
            "max_gap_s",
            "stuck_error",
            "stuck_speed",
            "filter_s",
            "default_dt",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"settle {name} must be positive, got {value}")
        for name in ("reversal_fraction", "backoff", "reverse_to_hold"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"settle {name} must be in [0, 1], got {getattr(self, name)}")
        if self.reversals < 2 or self.min_span_s < 0 or self.stuck_s < 0:
            raise ValueError(f"settle thresholds out of range: {self}")
        if not (0 < self.ramp_decay <= 1 and 0 <= self.ramp_floor <= 1):
            raise ValueError(
                f"settle ramp_decay must be in (0, 1] and ramp_floor in [0, 1]: {self}"
            )
        if self.progress < 0 or self.crossing_speed < 0 or self.creep_arrive_s < 0:
            raise ValueError(
                f"settle progress, crossing_speed and creep_arrive_s must be >= 0: {self}"
            )
        for name in ("memory_rate", "creep_rate", "arrive_decay", "fall_decay"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"settle {name} must be in (0, 1], got {getattr(self, name)}")
        if not (math.isfinite(self.fall_ramp) and self.fall_ramp >= 0):
            raise ValueError(f"settle fall_ramp must be >= 0, got {self.fall_ramp}")
        if not (math.isfinite(self.reversing_speed) and self.reversing_speed >= 0):
            raise ValueError(f"settle reversing_speed must be >= 0, got {self.reversing_speed}")
        if not (math.isfinite(self.coast_s) and self.coast_s >= 0 and self.coast_band > 0):
            raise ValueError(f"settle coast_s must be >= 0 and coast_band > 0: {self}")
        if not (math.isfinite(self.fall_gain) and self.fall_gain >= 1):
            raise ValueError(f"settle fall_gain must be >= 1, got {self.fall_gain}")
        if self.creep_hold < 0:
            raise ValueError(f"settle creep_hold must be >= 0, got {self.creep_hold}")
        if self.stuck_band <= 0 or self.noise_sigmas < 0 or self.arrive < 0:
            raise ValueError(f"settle stuck_band must be > 0, noise_sigmas and arrive >= 0: {self}")
        if not (self.jitter_true_speed >= 0 and self.jitter_noise_k > 0):
            raise ValueError(
                f"settle jitter_true_speed must be >= 0 and jitter_noise_k > 0: {self}"
            )
        if self.freeze < 0:
            raise ValueError(f"settle freeze must be >= 0, got {self.freeze}")
        if not set(self.prompt_joints) <= set(JOINT_LETTERS):
            raise ValueError(
                f"settle prompt_joints must be letters of {''.join(JOINT_LETTERS)}, "
                f"got {self.prompt_joints!r}"
            )
        if (
            self.latent_crossing_speed < 0
            or self.latent_periods < 0
            or self.onset_steps < 3
            or not 0 < self.onset_fraction <= 1
            or self.onset_error <= 0
        ):
            raise ValueError(f"settle latency settings out of range: {self}")

    @classmethod
    def from_param(cls, value: Any) -> SettleLaw | None:
        """`settle` as a factory parameter: false/0/None off, true/1 the defaults, a dict of
        field overrides (JSON through `--param settle={...}`)."""
        if value is None or value is False or value == 0:
            return None
        if value is True or value == 1:
            return cls()
        if isinstance(value, SettleLaw):
            return value
        if isinstance(value, dict):
            names = {f.name for f in fields(cls)}
            unknown = set(value) - names
            if unknown:
                raise ValueError(f"unknown settle fields: {', '.join(sorted(unknown))}")
            return cls(**value)
        raise ValueError(f"settle must be a bool, 0/1 or a dict of SettleLaw fields: {value!r}")
