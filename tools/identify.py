#!/usr/bin/env python3
"""Identify an Alpha 5 (virtual or real) through the driver and fit the twin to it.

    reach-sim --link /tmp/alpha5 --speed 4 &
    tools/identify.py --port /tmp/alpha5 --out arm.json            # excite, record, fit, report
    tools/identify.py --fit-only arm.log.npz --out arm.json        # refit a recorded log
    reach-sim --params arm.json ...                                # serve the fitted twin

Each joint in turn is driven in current mode through `reach_driver` (`ArmClient` with its
limits, barrier and watchdog on; `ControlLoop`, stream pacing, so time is the arm's) while
the other joints are held by a PID: adaptive relay swings at three speeds and a current chirp
(the fitting motions) and pseudo-random current steps and a second chirp at another pose (the
validation motions), each inside a window around its pose (the excitation backs off near the
window edges and above a speed limit), with a position-mode move to the segment's pose
before each. Ctrl-C leaves the arm in the driver's safe mode (zero velocity).

Two records of the excitation: PARAMS.log.npz (`reach_sim_bridge.fit.sysid.save_segments`: per
segment the loop's q, qdot, commands and measured currents on its tick grid, and each
command's transport delay measured from the driver's timestamps) and PARAMS.rrd (`--record`,
a Rerun recording through `reach_driver.recording`; `--fit-only` reads either). The fit is by
simulation (`reach_sim_bridge.fit.sysid`, docs/identification.md), with the delay measured, not
fitted (it trades off against the armature). Outputs: PARAMS.json in the `--params` format
with the fit under "_fit" (the loader ignores keys starting with _): per parameter its value
and 1-sigma uncertainty, the delays, R^2 and residual RMS; and a report
PARAMS.report/report.md with PNG figures (measured vs nominal twin vs fitted twin), with
`--truth HIDDEN.json --check-controller pid,ddpg` the controller gap (tools/twin_gap.py).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from protocol import Mode, PacketID
from protocol.alpha5 import (
    FACTORY_POSITION_LIMITS,
    JOINT_LETTERS,
    JOINTS,
    N_JOINTS,
    TORQUE_PER_AMP_NM,
)
from reach_driver import ArmClient, ControlLoop, DriverError, SafetyConfig, open_transport
from reach_driver.controllers import ControlState
from reach_driver.errors import NoResponseError, RequestTimeoutError
from reach_driver.interfaces import DEFAULT_BAUD
from reach_driver.records import StepRecord
from reach_sim_bridge.fit.sysid import (
    DEFAULT_WINDOW_S,
    FitResult,
    LinkTiming,
    Replay,
    Segment,
    fit_arm,
    link_delays,
    load_segments,
    quality,
    ref_name,
    save_segments,
    segment_delays,
    segment_from_index,
    tune_offsets,
)
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams, load_arm_params, save_arm_params

K_MA = np.asarray(TORQUE_PER_AMP_NM) / 1000.0  # N m per mA, E D C B
#: The middle of the factory envelope: the pose every identification starts and ends at.
HOME = np.array(
    [0.5 * (FACTORY_POSITION_LIMITS[d][0] + FACTORY_POSITION_LIMITS[d][1]) for d in JOINTS]
)
#: Fitting poses P1, P2 and the validation pose P3 (offsets from HOME, rad): D and C at other
#: angles load them differently with gravity.
POSE_OFFSETS = {
    "P1": np.zeros(4),
    "P2": np.array([0.5, -0.45, 0.5, 0.8]),
    "P3": np.array([-0.5, 0.45, -0.45, -0.8]),
}
WINDOW = np.array([0.35, 0.35, 0.35, 0.6])  # rad each side of the pose, the excited joint
GUARD = 0.15  # rad beyond the window: the excited joint is servoed back to its pose
SPEED_CAP = np.array([0.45, 0.45, 0.45, 0.75])  # rad/s, under the factory rate limits
SPEED_FILTER_S = 0.1  # s: the relay judges its speed on readings low-passed this much
STALL_CHECK_S = 0.5  # s: under 0.3 of the aimed progress in this gets the relay more current
HOLD_KP = np.array([3000.0, 3000.0, 3000.0, 300.0])  # mA/rad
HOLD_KD = np.array([200.0, 200.0, 200.0, 20.0])  # mA s/rad
HOLD_KI = np.array([6000.0, 6000.0, 6000.0, 600.0])  # mA/(rad s)
HOLD_I_MAX = np.array([250.0, 250.0, 250.0, 60.0])  # mA the integral may add
CHIRP_SPRING = np.array([600.0, 600.0, 600.0, 60.0])  # mA/rad centring the chirped joint
CHIRP_DAMP = np.array([20.0, 20.0, 20.0, 2.0])  # mA s/rad


@dataclass(frozen=True)
class Wave:
    """One excitation of one joint: relay (speed target), chirp, or random steps."""

    kind: str  # "relay" | "chirp" | "steps"
    pose: str  # "P1" | "P2" | "P3"
    seconds: float
    role: str  # "fit" | "validate"
    speed: float = 0.25  # relay: rad/s peak speed aimed for
    f0: float = 0.3  # chirp: Hz
    f1: float = 3.0
    gain: float = 1.5  # chirp: amplitude / the joint's relay amplitude; steps: spread
    seed: int = 0

    @property
    def label(self) -> str:
        detail = {
            "relay": f"{self.speed:g} rad/s",
            "chirp": f"{self.f0:g}-{self.f1:g} Hz",
            "steps": f"seed {self.seed}",
        }[self.kind]
        return f"{self.kind} {detail} at {self.pose}"


def plan(scale: float = 1.0) -> list[Wave]:
    """The segments of one joint (arm seconds scale with `scale`)."""
    s = scale
    return [
        Wave("relay", "P1", 8.0 * s, "fit", speed=0.15),
        Wave("relay", "P1", 8.0 * s, "fit", speed=0.35),
        Wave("chirp", "P1", 8.0 * s, "fit", f0=0.3, f1=5.0, gain=2.0),
        Wave("relay", "P2", 8.0 * s, "fit", speed=0.25),
        Wave("steps", "P3", 8.0 * s, "validate", gain=0.4, seed=1),
        Wave("chirp", "P3", 6.0 * s, "validate", f0=0.5, f1=2.5, gain=1.3),
    ]


def pose(name: str) -> np.ndarray:
    return HOME + POSE_OFFSETS[name]


@dataclass
class Amplitudes:
    """The excitation current found per joint (mA), adapted by the relay swings."""

    nominal: ArmParams = field(default_factory=ArmParams)
    ratio: dict[int, float] = field(default_factory=dict)  # found / nominal estimate
    found: dict[int, float] = field(default_factory=dict)  # the last relay's amplitude

    def nominal_for(self, joint: int, speed: float) -> float:
        """What the nominal twin needs to hold `speed` against friction (mA)."""
        p = self.nominal
        torque = p.frictionloss[joint] + p.damping[joint] * speed
        return float(torque / K_MA[joint])

    def start(self, joint: int, speed: float) -> float:
        """A relay's first amplitude: the nominal estimate, corrected by earlier relays."""
        return self.nominal_for(joint, speed) * self.ratio.get(joint, 1.0)

    def learn(self, joint: int, speed: float, amplitude: float) -> None:
        self.ratio[joint] = amplitude / self.nominal_for(joint, speed)
        self.found[joint] = amplitude

    def reference(self, joint: int) -> float:
        """The current that chirps and steps are scaled by (mA)."""
        return self.found.get(joint, self.start(joint, 0.25))


class Excitation:
    """A `Controller` exciting one joint with `wave` around `center` while holding the
    others there (PID), with the nominal twin's gravity as feed-forward for all joints."""

    def __init__(
        self,
        joint: int,
        wave: Wave,
        center: np.ndarray,
        period: float,
        amplitude: float,
        amp_max: float,
        gravity: Any,
    ) -> None:
        self.joint = joint
        self.wave = wave
        self.center = np.asarray(center, dtype=float)
        self.period = period
        self.amplitude = float(amplitude)
        self.amp_max = float(amp_max)
        self.gravity = gravity
        self.rng = np.random.default_rng(wave.seed)
        self.reset()

    def reset(self) -> None:
        self.integral = np.zeros(N_JOINTS)
        self.direction = 1.0
        self.peak = 0.0
        self.pass_t = 0.0
        self.stall_t = 0.0
        self.stall_x: float | None = None
        self.speed = 0.0  # the joint's speed readings, low-passed (SPEED_FILTER_S)
        self.step_end = -1.0
        self.step_level = 0.0
        self.flips = 0

    def _hold(self, q: np.ndarray, qdot: np.ndarray) -> np.ndarray:
        err = self.center - q
        self.integral = np.clip(
            self.integral + HOLD_KI * err * self.period, -HOLD_I_MAX, HOLD_I_MAX
        )
        return HOLD_KP * err - HOLD_KD * qdot + self.integral

    def act(self, state: ControlState, target: np.ndarray) -> np.ndarray:
        q, qdot, t = state.q, state.qdot, float(state.t)
        j, w = self.joint, self.wave
        ff = -np.asarray(self.gravity(q)) / K_MA  # mA holding the nominal twin's weight
        out = ff + self._hold(q, qdot)
        x = q[j] - self.center[j]
        v = qdot[j]
        if abs(x) > WINDOW[j] + GUARD:
            # Outside the window and the guard band: servo back (the hold law, this joint).
            return out
        self.integral[j] = 0.0
        if w.kind == "relay":
            u = self._relay(x, v, t)
        elif w.kind == "chirp":
            tt = t
            phase = 2 * math.pi * (w.f0 * tt + 0.5 * (w.f1 - w.f0) * tt * tt / w.seconds)
            amp = w.gain * self.amplitude
            u = amp * math.sin(phase) - CHIRP_SPRING[j] * x - CHIRP_DAMP[j] * v
        else:
            u = self._steps(x, t)
        if abs(x) > WINDOW[j] and u * x > 0:
            u = 0.0  # never push further out past the window edge
        if abs(v) > SPEED_CAP[j] and u * v > 0:
            u = 0.0  # coast down from above the speed cap
        out[j] = ff[j] + float(np.clip(u, -self.amp_max, self.amp_max))
        return out

    def _relay(self, x: float, v: float, t: float) -> float:
        # Noisy readings (3x the standard noise: 0.06 rad/s) once passed for motion: their
        # peak read 0.2 rad/s on a joint stuck behind 6.6 N m, so its current never rose.
        # The peak is taken on low-passed speeds and a stall from the angle's progress.
        j, w = self.joint, self.wave
        self.speed += (v - self.speed) * min(1.0, self.period / SPEED_FILTER_S)
        self.peak = max(self.peak, abs(self.speed))
        edge = WINDOW[j] * 0.9
        if self.stall_x is None:
            self.stall_t, self.stall_x = t, x
        if (self.direction > 0 and x > edge) or (self.direction < 0 and x < -edge):
            self.direction = -self.direction
            self.flips += 1
            self._adapt(w.speed)
            self.peak = 0.0
            self.pass_t = t
            self.stall_t, self.stall_x = t, x
        elif t - self.stall_t >= STALL_CHECK_S:
            # Not moving: friction above what was tried; more current.
            if abs(x - self.stall_x) < 0.3 * w.speed * (t - self.stall_t):
                self.amplitude = min(self.amplitude * 1.3, self.amp_max)
            self.stall_t, self.stall_x = t, x
        return self.direction * self.amplitude

    def _adapt(self, speed: float) -> None:
        if self.peak < 0.85 * speed:
            self.amplitude = min(self.amplitude * 1.2, self.amp_max)
        elif self.peak > 1.15 * speed:
            self.amplitude *= 0.85

    def _steps(self, x: float, t: float) -> float:
        j, w = self.joint, self.wave
        if t >= self.step_end:
            self.step_end = t + float(self.rng.uniform(0.4, 1.0))
            if self.rng.random() < 0.25:
                self.step_level = 0.0
            else:
                sign = 1.0 if self.rng.random() < 0.5 else -1.0
                if abs(x) > 0.5 * WINDOW[j]:
                    sign = -math.copysign(1.0, x)
                spread = float(self.rng.uniform(1.0 - w.gain, 1.0 + w.gain))
                self.step_level = sign * spread * self.amplitude
        if abs(x) > 0.9 * WINDOW[j] and self.step_level * x > 0:
            self.step_level = -self.step_level
        return self.step_level


# -- driving the arm -----------------------------------------------------------------------


RETRIES = 4  # per segment, after a watchdog trip or a feedback stall
MOVE_SILENCE_S = 3.0  # a move gives up when the arm has not answered for this long


def move_to(client: ArmClient, target: np.ndarray, timeout_s: float = 30.0) -> float:
    """Position-mode move to `target` (checked by the driver); wall seconds it took."""
    for dev, value in zip(JOINTS, target, strict=True):
        client.guard.check(int(dev), _position_kind(), float(value))
    t0 = time.monotonic()
    client.set_mode(JOINTS, Mode.POSITION)
    client.command_positions(target)
    deadline = t0 + timeout_s
    resend = t0 + 1.0
    quiet_since: float | None = None
    while True:
        try:
            state = client.read_joints((PacketID.POSITION, PacketID.VELOCITY))
        except (RequestTimeoutError, NoResponseError) as exc:
            # A loaded host (or a busy line) can miss a few replies; the move goes on (the
            # arm holds its position target) unless the arm stays silent for MOVE_SILENCE_S.
            now = time.monotonic()
            quiet_since = now if quiet_since is None else quiet_since
            if now - quiet_since > MOVE_SILENCE_S or now > deadline:
                raise DriverError(f"the arm stopped answering during a move: {exc}") from None
            continue
        quiet_since = None
        err = np.abs(target - state.q)
        if np.all(err < 0.01) and np.all(np.abs(state.qdot) < 0.03):
            break
        faults = client.blocking_faults()
        if faults:
            client.safe_stop(JOINTS)
            raise DriverError(f"fault during a move, joints stopped: {faults}")
        now = time.monotonic()
        if now > deadline:
            raise DriverError(f"move to {target.round(3).tolist()} timed out ({err.max():.3f})")
        if now > resend:  # a lost packet must not stall the move
            client.command_positions(target)
            resend = now + 1.0
        time.sleep(0.02)
    return time.monotonic() - t0


def _position_kind() -> Any:
    from reach_driver import LimitKind

    return LimitKind.POSITION


@dataclass
class StepStamps:
    """The driver's timestamps of each step of one run (`ControlLoop`'s `on_step`): the arm
    time of the tick, the host time its state was complete and the host time the command
    was written (the hook runs right after the write)."""

    t: list[float] = field(default_factory=list)
    received: list[float] = field(default_factory=list)
    written: list[float] = field(default_factory=list)
    latency: list[float] = field(default_factory=list)
    state_age: list[float] = field(default_factory=list)
    good: list[int] = field(default_factory=list)
    bad: list[int] = field(default_factory=list)

    def on_step(self, r: StepRecord) -> None:
        now = time.monotonic()
        self.t.append(r.t)
        self.written.append(now)
        self.received.append(now - r.latency_s)
        self.latency.append(r.latency_s)
        self.state_age.append(r.state_age_s)
        self.good.append(r.good_frames)
        self.bad.append(r.bad_frames)

    def timing(self, trace_t: np.ndarray, dt: float) -> LinkTiming | None:
        """The measured delays per command row of a trace on the tick grid `dt` (None with
        fewer than two steps: the delay is then left to the fit alone). A tick the loop
        skipped (it was late and took the newer state) sent no command: its row holds the
        previous command and is NaN (the replay lands it with the one before)."""
        if len(self.t) < 2:
            return None
        t = np.asarray(self.t)
        measured = link_delays(t, np.asarray(self.received), np.asarray(self.written))
        n = len(trace_t) - 1
        rows = np.rint(t / dt).astype(int) + 1  # the command sent at tick k is row k + 1
        delays = np.full(n + 1, np.nan)
        keep = (rows >= 1) & (rows <= n)
        delays[rows[keep]] = measured.delays_s[1:][keep]
        return replace(measured, delays_s=delays)  # NaN: a skipped tick, no command sent


@dataclass
class Session:
    segments: list[Segment] = field(default_factory=list)
    arm_seconds: float = 0.0  # in current mode, exact (ticks)
    move_seconds: float = 0.0  # in moves, wall x the measured arm speed
    arm_speed: float = 1.0
    retries: int = 0  # segments run again after a watchdog trip (a stalled host)


class ExcitationRecorder:
    """The excitation as a Rerun recording (.rrd), written with `reach_driver.recording` (the
    entities `reach-driver run --record` writes, so `reach-driver inspect` and the viewer
    read it): every tick of every segment on one arm-time timeline, an event where each
    segment starts, the link's latency and state age per step, and at the end a summary whose
    `segments` index (name, joint, role, first step, rows, measured link delays) lets
    `load_recording` rebuild the segments exactly. The file is opened before the arm moves
    (an unwritable path fails first) and the segments, from their traces (the rows the fit
    uses), are logged when the excitation ends or stops (Ctrl-C, an error): encoding them
    while the control loop runs took CPU from it on a loaded 2-core host. A write error is
    reported once and stops the recording; the identification goes on (the .npz log is the
    fit's own copy)."""

    def __init__(self, path: Path, metadata: dict[str, Any], console: Console) -> None:
        from reach_driver import recording

        self._recording = recording
        self.path = path
        self.console = console
        self.failed: str | None = None
        self.index: list[dict[str, Any]] = []
        self.step = 0
        self._pending: list[tuple[Segment, np.ndarray, float, StepStamps]] = []
        try:
            self._rec: Any = recording.RunRecorder(
                path,
                metadata={"source": "tools/identify.py", **metadata},
                warn=lambda msg: console.print(f"[yellow]warning[/]: {msg}"),
            )
            self._rec.log_event("start")
        except Exception as exc:  # rerun raises RuntimeError for sink errors, Python OSError
            raise DriverError(f"cannot record to {path}: {exc}") from None

    def _fail(self, exc: Exception) -> None:
        rec, self._rec = self._rec, None
        self.failed = f"writing {self.path} failed: {type(exc).__name__}: {exc}"
        self.console.print(
            f"[yellow]warning[/]: {self.failed}; recording stopped, the identification goes on"
        )
        if rec is not None:
            try:
                rec.abandon()
            except Exception:
                pass

    def add(self, seg: Segment, center: np.ndarray, t0: float, stamps: StepStamps) -> None:
        """Keep one finished segment (from arm time `t0` on) for `close` to log."""
        self._pending.append((seg, center, t0, stamps))

    def _log(self, seg: Segment, center: np.ndarray, t0: float, stamps: StepStamps) -> None:
        """Log one segment (its ticks are rows 0..n)."""
        rec = self._rec
        if rec is None:
            return
        recording = self._recording
        n = seg.ticks
        current = seg.current_mA if seg.current_mA is not None else np.full_like(seg.q, np.nan)
        try:
            rec.log_event(
                f"segment {seg.name} ({seg.role}): {seg.meta.get('wave', '')}", t=t0, step=self.step
            )
            for k in range(n + 1):
                t = t0 + k * seg.period
                rec.log_step(
                    recording.StepSample(
                        t=t,
                        step=self.step + k,
                        q=seg.q[k],
                        qdot=seg.qdot[k],
                        target=center,
                        current_cmd_mA=seg.command_mA[k + 1] if k < n else np.zeros(N_JOINTS),
                        current_meas_mA=current[k],
                    )
                )
                if k < len(stamps.t):
                    rec.log_link(
                        t,
                        self.step + k,
                        stamps.good[k],
                        stamps.bad[k],
                        stamps.state_age[k],
                        stamps.latency[k],
                    )
        except Exception as exc:
            self._fail(exc)
            return
        self.index.append(
            {
                "name": seg.name,
                "joint": seg.joint,
                "role": seg.role,
                "period": seg.period,
                "meta": seg.meta,
                "first_step": self.step,
                "rows": n + 1,
                "t0": t0,
                "command_row0": seg.command_mA[0].tolist(),
                "link_delay_s": None
                if seg.link_delay_s is None
                else [None if not math.isfinite(v) else v for v in seg.link_delay_s.tolist()],
            }
        )
        self.step += n + 1

    def close(self, header: dict[str, Any]) -> None:
        """Log the segments kept, the index and the end; close the file."""
        for item in self._pending:
            self._log(*item)
        self._pending.clear()
        rec = self._rec
        if rec is None:
            return
        try:
            rec.log_summary({"identification": header, "segments": self.index})
            rec.log_event("stop")
            rec.close()
            self._rec = None
        except Exception as exc:
            self._fail(exc)


def load_recording(path: Path) -> list[Segment]:
    """The segments of an excitation recorded by `ExcitationRecorder` (ValueError saying what
    is missing: a recording cut before its end has its steps but no index)."""
    from reach_driver.rrd_summary import read_recording

    run = read_recording(path)
    index = run.summary.get("segments") if isinstance(run.summary, dict) else None
    if not isinstance(index, list) or not index:
        raise ValueError(
            f"{path}: no identification index (not written by identify.py, or cut before the "
            f"excitation ended; its .npz log has the finished segments)"
        )
    rows_at = {int(s): i for i, s in enumerate(run.step)}
    out = []
    for meta in index:
        first, rows = int(meta["first_step"]), int(meta["rows"])
        try:
            sel = np.array([rows_at[first + k] for k in range(rows)])
        except KeyError as exc:
            raise ValueError(f"{path}: segment {meta['name']} lacks step {exc}") from None
        if run.qdot is None:
            raise ValueError(f"{path}: no velocities recorded")
        command = np.empty((rows, N_JOINTS))
        command[0] = meta["command_row0"]
        command[1:] = run.current_cmd[sel[:-1]]
        delays = meta.get("link_delay_s")
        out.append(
            segment_from_index(
                meta,
                run.q[sel],
                run.qdot[sel],
                command,
                run.current_meas[sel],
                None
                if delays is None
                else np.array([np.nan if v is None else v for v in delays], dtype=float),
            )
        )
    return out


def excite(
    client: ArmClient,
    joints: Sequence[int],
    waves: Sequence[Wave],
    rate_hz: float,
    console: Console,
    session: Session,
    max_current: np.ndarray,
    recorder: ExcitationRecorder | None = None,
) -> None:
    """Run every wave on every joint, appending to `session` (and `recorder`) as segments
    finish."""
    period = 1.0 / rate_hz
    twin = Alpha5Arm()
    amps = Amplitudes()
    total = sum(w.seconds for w in waves) * len(joints)
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f} arm s"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[detail]}"),
        console=console,
    ) as progress:
        task = progress.add_task("identify", total=total, detail="")
        for j in joints:
            letter = JOINT_LETTERS[j]
            for k, wave in enumerate(waves):
                center = pose(wave.pose)
                for attempt in range(RETRIES + 1):
                    progress.update(task, detail=f"{letter}: move to {wave.pose}")
                    wall = move_to(client, center)
                    session.move_seconds += wall * session.arm_speed
                    start = amps.start(j, wave.speed) if wave.kind == "relay" else amps.reference(j)
                    controller = Excitation(
                        j,
                        wave,
                        center,
                        period,
                        amplitude=start,
                        amp_max=0.8 * float(max_current[j]),
                        gravity=twin.gravity_torque,
                    )
                    progress.update(task, detail=f"{letter}: {wave.label}")
                    stamps = StepStamps()
                    loop = ControlLoop(client, controller, period, on_step=stamps.on_step)
                    summary = loop.run(center, wave.seconds)
                    if not summary.error:
                        break
                    stalled = "feedback stopped" in summary.error
                    if (client.tripped is None and not stalled) or attempt == RETRIES:
                        raise DriverError(f"{letter} {wave.label}: {summary.stopped_by}")
                    # The host stalled past the watchdog (the arm went to zero velocity) or
                    # long enough for the loop to give up on the feedback (the loop left the
                    # arm safe): say so, re-arm and run the segment again from its pose.
                    session.retries += 1
                    why = client.tripped or summary.error
                    console.print(f"[yellow]{letter} {wave.label}: {why}; again[/]")
                    if client.tripped is not None:
                        client.rearm()
                trace = summary.trace
                if trace is None:
                    raise DriverError(f"{letter} {wave.label}: no trace")
                session.arm_speed = summary.timing.arm_speed or session.arm_speed
                if wave.kind == "relay":
                    amps.learn(j, wave.speed, controller.amplitude)
                timing = stamps.timing(trace.t, trace.dt)
                segment = Segment(
                    name=f"{letter}{k}-{wave.kind}-{wave.pose}",
                    joint=j,
                    role=wave.role,
                    period=trace.dt,
                    q=trace.q,
                    qdot=trace.qdot,
                    command_mA=trace.command_mA,
                    current_mA=trace.current_mA,
                    meta={
                        "wave": wave.label,
                        "pose": center.tolist(),
                        "amplitude_mA": controller.amplitude,
                        "flips": controller.flips,
                        "saturated_steps": summary.saturated_steps,
                        "barrier_steps": summary.barrier_steps,
                        "left_in": summary.left_in,
                        "link_delay_p50_ms": None if timing is None else timing.p50_s * 1e3,
                        "link_delay_p99_ms": None if timing is None else timing.p99_s * 1e3,
                    },
                    link_delay_s=None if timing is None else timing.delays_s,
                )
                session.segments.append(segment)
                if recorder is not None:
                    recorder.add(
                        segment, center, session.arm_seconds + session.move_seconds, stamps
                    )
                session.arm_seconds += trace.t[-1]
                progress.update(task, advance=wave.seconds)
        progress.update(task, detail="home")
        session.move_seconds += move_to(client, HOME) * session.arm_speed


# -- fitting and reporting -----------------------------------------------------------------


@dataclass
class FitOutcome:
    params: ArmParams
    delay_s: float
    results: dict[int, FitResult]
    nominal_quality: dict[str, Any]
    fitted_quality: dict[str, Any]
    fit_seconds: float
    quantum_s: float = 0.0
    fit_starts: bool = True
    # The segments as each twin was scored ("nominal", "fitted"): with their delay offsets.
    scored: dict[str, list[Segment]] = field(default_factory=dict)


def fit(
    segments: Sequence[Segment],
    console: Console,
    window_s: float = DEFAULT_WINDOW_S,
    max_iter: int = 12,
    fit_starts: bool = True,
) -> tuple[FitOutcome, Replay]:
    t0 = time.monotonic()
    replay = Replay(window_s=window_s)
    nominal = ArmParams()

    def on_joint(j: int, r: FitResult) -> None:
        cells = ", ".join(
            f"{ref_name(ref)} {v:.4g} +- {s:.2g}"
            for ref, v, s in zip(r.refs, r.values, r.sigma, strict=True)
        )
        console.print(
            f"fitted {JOINT_LETTERS[j]} in {r.iterations} iterations ({r.rollouts} rollouts): "
            f"{cells}"
        )

    def on_iter(j: int, it: int, cost: float) -> None:
        console.print(f"  {JOINT_LETTERS[j]} iteration {it}: cost {cost:.4g}", style="dim")

    arm_fit = fit_arm(
        replay,
        segments,
        nominal,
        max_iter=max_iter,
        on_joint=on_joint,
        on_iteration=on_iter,
        fit_starts=fit_starts,
    )
    params = arm_fit.params
    nom_q: dict[str, Any] = {}
    fit_q: dict[str, Any] = {}
    # Each twin is scored with the delay offsets that suit it best (one per segment, the
    # part of the delay the timestamps do not see; tuned on the 1 s windows): a nuisance of
    # the measurement, not a parameter of the arm, so the nominal twin gets the same chance.
    scored: dict[str, list[Segment]] = {"nominal": [], "fitted": []}
    for role in ("fit", "validate"):
        for j in sorted({s.joint for s in segments}):
            segs = [s for s in segments if s.joint == j and s.role == role]
            if not segs:
                continue
            key = f"{role}/{JOINT_LETTERS[j]}"
            for twin, p, table in (("nominal", nominal, nom_q), ("fitted", params, fit_q)):
                ready = tune_offsets(replay, p, segs)
                scored[twin].extend(ready)
                for label, w in (("window", window_s), ("open_loop", 0.0)):
                    table.setdefault(key, {})[label] = quality(replay, p, 0.0, ready, w).as_dict()
    outcome = FitOutcome(
        params,
        arm_fit.delay_s,
        arm_fit.results,
        nom_q,
        fit_q,
        time.monotonic() - t0,
        quantum_s=arm_fit.quantum_s,
        fit_starts=fit_starts,
        scored=scored,
    )
    return outcome, replay


def fit_metadata(
    outcome: FitOutcome, session: Session | None, window_s: float, log_path: Path | None
) -> dict[str, Any]:
    params_table: dict[str, Any] = {}
    for r in outcome.results.values():
        params_table.update(r.table())
    return {
        "method": "least squares over MuJoCo rollouts (reach_sim_bridge.fit.sysid), multiple "
        f"shooting over {window_s:g} s windows"
        f"{' with fitted starts' if outcome.fit_starts else ''}; docs/identification.md",
        "parameters": params_table,
        "delay_s": outcome.delay_s,
        "delay_note": "median of the delays the replay used (per command: measured from the "
        "driver's timestamps plus a per-segment offset); not an arm parameter",
        "command_step_s": outcome.quantum_s,
        "delay_offsets_ms": {
            seg.name: round(seg.offset_s * 1e3, 3) for seg in outcome.scored.get("fitted", [])
        },
        "quality_fitted": outcome.fitted_quality,
        "quality_nominal": outcome.nominal_quality,
        "sigma_note": "1 sigma from sqrt(diag(s^2 (J^T J)^-1)) at the optimum; residuals are "
        "correlated in time, so these understate the true uncertainty",
        "arm_seconds": None if session is None else session.arm_seconds + session.move_seconds,
        "log": None if log_path is None else str(log_path),
        "fit_seconds": outcome.fit_seconds,
    }


def _scored(outcome: FitOutcome, twin: str, seg: Segment) -> Segment:
    """`seg` with the delay offset it was scored with for `twin` (itself if not scored)."""
    for x in outcome.scored.get(twin, []):
        if x.name == seg.name:
            return x
    return seg


def write_report(
    outcome: FitOutcome,
    replay: Replay,
    segments: Sequence[Segment],
    out_dir: Path,
    window_s: float,
    session: Session | None,
    truth: ArmParams | None,
) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    nominal = ArmParams()
    lines = ["# Identification report", ""]
    if session is not None:
        lines += [
            f"Arm time: {session.arm_seconds:.1f} s excitation + ~{session.move_seconds:.1f} s "
            f"moves; fit: {outcome.fit_seconds:.0f} s CPU-bound wall time.",
            "",
        ]
    delays = np.concatenate([segment_delays(x) for x in outcome.scored.get("fitted", segments)])
    lines += [
        f"Transport delay (measured per command from the driver's timestamps, plus a "
        f"per-segment offset): median {1e3 * float(np.median(delays)):.1f} ms, 99th percentile "
        f"{1e3 * float(np.percentile(delays, 99)):.1f} ms; the arm takes commands every "
        f"{outcome.quantum_s * 1e3:g} ms (chosen by the fit).",
        "",
    ]
    header = "| parameter | nominal | fitted | 1 sigma |"
    rule = "|---|---|---|---|"
    if truth is not None:
        header += " truth | error |"
        rule += "---|---|"
    lines += ["## Parameters", "", header, rule]
    for r in outcome.results.values():
        for ref, v, s in zip(r.refs, r.values, r.sigma, strict=True):
            name, idx = ref
            nom = 0.005 if name == "delay_s" else getattr(nominal, name)[idx]
            row = f"| {ref_name(ref)} | {nom:.4g} | {v:.4g} | {s:.2g} |"
            if truth is not None:
                if name == "delay_s":
                    row += " - | - |"
                else:
                    tv = getattr(truth, name)[idx]
                    # a frictionless joint has no relative error: give the difference
                    err = f"{100 * (v - tv) / tv:+.1f} %" if tv != 0 else f"{v - tv:+.2g} (abs)"
                    row += f" {tv:.4g} | {err} |"
            lines.append(row)
    lines += [
        "",
        f"## Prediction quality ({window_s:g} s windows from the measured state, and open "
        "loop over whole segments)",
        "",
        "| motions / joint | twin | R^2 window | RMS window mrad | R^2 open loop | "
        "RMS open loop mrad |",
        "|---|---|---|---|---|---|",
    ]
    for key in outcome.fitted_quality:
        for twin, table in (
            ("nominal", outcome.nominal_quality),
            ("fitted", outcome.fitted_quality),
        ):
            qw, qo = table[key]["window"], table[key]["open_loop"]
            lines.append(
                f"| {key} | {twin} | {qw['r2']:.4f} | {qw['rms_mrad']:.2f} | {qo['r2']:.4f} | "
                f"{qo['rms_mrad']:.2f} |"
            )
    lines += ["", "## Validation motions", ""]
    for seg in segments:
        if seg.role != "validate":
            continue
        j = seg.joint
        t = np.arange(seg.ticks + 1) * seg.period
        fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
        nom_seg = _scored(outcome, "nominal", seg)
        fit_seg = _scored(outcome, "fitted", seg)
        nom_r = replay.simulate(nominal, 0.0, nom_seg, window_s)
        fit_r = replay.simulate(outcome.params, 0.0, fit_seg, window_s)
        axes[0].plot(t, seg.q[:, j], "k", lw=1.5, label="measured")
        axes[0].plot(t, nom_r.q[:, j], "C1", lw=1, label="nominal twin")
        axes[0].plot(t, fit_r.q[:, j], "C0--", lw=1, label="fitted twin")
        axes[0].set_ylabel(f"{JOINT_LETTERS[j]} angle (rad)")
        axes[0].legend(loc="best", fontsize=8)
        axes[1].plot(t, 1e3 * (nom_r.q[:, j] - seg.q[:, j]), "C1", lw=1, label="nominal")
        axes[1].plot(t, 1e3 * (fit_r.q[:, j] - seg.q[:, j]), "C0", lw=1, label="fitted")
        axes[1].set_ylabel("error (mrad)")
        axes[1].legend(loc="best", fontsize=8)
        axes[2].plot(t, seg.command_mA[:, j], "k", lw=1)
        axes[2].set_ylabel("command (mA)")
        axes[2].set_xlabel(f"arm time (s); {window_s:g} s windows start from the measured state")
        fig.suptitle(f"{seg.name}: {seg.meta.get('wave', '')}")
        fig.tight_layout()
        png = out_dir / f"{seg.name}.png"
        fig.savefig(png, dpi=90)
        plt.close(fig)
        lines += [f"![{seg.name}]({png.name})", ""]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# -- command line --------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="identify.py",
        description=__doc__.split("\n\n")[0] if __doc__ else "",
        epilog="Method: docs/identification.md. Real arms: docs/hil.md (identification).",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--port", help="the arm, as reach-driver --port takes it")
    src.add_argument(
        "--fit-only",
        type=Path,
        metavar="LOG",
        help="refit a recorded excitation: its .npz log or its .rrd recording",
    )
    p.add_argument("--out", type=Path, required=True, metavar="PARAMS.json")
    p.add_argument("--log", type=Path, metavar="LOG.npz", help="default: PARAMS.log.npz")
    p.add_argument(
        "--record",
        type=Path,
        metavar="FILE.rrd",
        help="the excitation as a Rerun recording (default: PARAMS.rrd)",
    )
    p.add_argument("--no-record", action="store_true", help="write no .rrd")
    p.add_argument("--report", type=Path, metavar="DIR", help="default: PARAMS.report/")
    p.add_argument("--no-report", action="store_true")
    p.add_argument(
        "--joints", default="E,D,C,B", help="joints to identify, comma-separated (default all)"
    )
    p.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="scale every segment's length (default 1: 46 arm s per joint, ~4 min for "
        "four joints with the moves)",
    )
    p.add_argument("--rate", type=float, default=50.0, help="control rate, Hz (default 50)")
    p.add_argument("--baud", type=int, default=DEFAULT_BAUD, help="serial baud rate")
    p.add_argument(
        "--max-current",
        type=float,
        default=300.0,
        metavar="MA",
        help="cap on the excitation's current per joint in mA (default 300; B at most "
        "half of it), also given to the driver as its current limit",
    )
    p.add_argument("--watchdog", type=float, default=0.2, metavar="S")
    p.add_argument("--window", type=float, default=DEFAULT_WINDOW_S, metavar="S")
    p.add_argument("--iterations", type=int, default=12)
    p.add_argument(
        "--no-fit-starts",
        action="store_true",
        help="start each replay window from the readings as they are (default: the windows' "
        "starting angle and speed are fitted beside the arm; see docs/identification.md)",
    )
    p.add_argument(
        "--check-controller",
        metavar="NAMES",
        help="with --truth: run these controllers (comma-separated, e.g. pid,ddpg) on the "
        "hidden arm, the fitted twin and the nominal twin on the same episodes and report "
        "the energy and settling-time gaps (tools/twin_gap.py)",
    )
    p.add_argument("--check-episodes", type=int, default=6, metavar="N")
    p.add_argument(
        "--truth",
        type=Path,
        metavar="PARAMS.json",
        help="a virtual arm's true parameters: the report adds the error of each",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = Console(stderr=True)
    out: Path = args.out
    log_path: Path = args.log or out.with_suffix(".log.npz")
    report_dir: Path = args.report or out.with_suffix(".report")
    record_path: Path | None = None if args.no_record else (args.record or out.with_suffix(".rrd"))
    try:
        joints = [JOINT_LETTERS.index(x.strip().upper()) for x in args.joints.split(",")]
    except ValueError:
        console.print(f"[red]error:[/] --joints takes letters of E D C B, got {args.joints!r}")
        return 2
    truth = load_arm_params(args.truth) if args.truth else None
    session: Session | None = None
    if args.fit_only is not None:
        try:
            if args.fit_only.suffix == ".rrd":
                segments = load_recording(args.fit_only)
            else:
                segments = load_segments(args.fit_only)
        except (OSError, ValueError, KeyError) as exc:
            console.print(f"[red]cannot read {args.fit_only}:[/] {exc}")
            return 2
        log_path = args.fit_only
    else:
        max_current = np.array([1.0, 1.0, 1.0, 0.5]) * args.max_current
        safety = SafetyConfig(
            watchdog_s=args.watchdog,
            chatter=None,  # the relay swings are a deliberate bang-bang about a centre
            current_limits_mA={int(d): float(m) for d, m in zip(JOINTS, max_current, strict=True)},
        )
        session = Session()
        try:
            client = ArmClient(open_transport(args.port, baud=args.baud), safety=safety)
            client.start()
        except (DriverError, ValueError) as exc:
            console.print(f"[red]no arm:[/] {exc}")
            return 4
        recorder: ExcitationRecorder | None = None
        if record_path is not None:
            try:
                recorder = ExcitationRecorder(
                    record_path,
                    {"port": args.port, "rate_hz": args.rate, "scale": args.scale},
                    console,
                )
            except DriverError as exc:
                client.close()
                console.print(f"[red]error:[/] {exc}")
                return 2
        interrupted = False
        try:
            faults = client.blocking_faults()
            if faults:
                console.print(f"[red]arm reports faults, not moving:[/] {faults}")
                return 1
            excite(
                client,
                joints,
                plan(args.scale),
                args.rate,
                console,
                session,
                max_current,
                recorder,
            )
        except KeyboardInterrupt:
            interrupted = True
        except DriverError as exc:
            console.print(f"[red]identification stopped:[/] {exc}")
            interrupted = True
        finally:
            try:
                client.safe_stop(JOINTS)
                left = "zero_velocity"
            except DriverError as exc:
                left = f"unknown ({exc})"
            client.close()
            console.print(f"arm left in {left}")
            header = {
                "port": args.port,
                "rate_hz": args.rate,
                "scale": args.scale,
                "arm_seconds": session.arm_seconds,
                "move_seconds": session.move_seconds,
                "complete": not interrupted,
                "retries": session.retries,
            }
            if session.segments:
                save_segments(session.segments, log_path, header)
                console.print(f"log {log_path} ({len(session.segments)} segments)")
            if recorder is not None:
                recorder.close(header)
                if recorder.failed is None:
                    console.print(f"recording {record_path} ({recorder.step} steps)")
        if interrupted:
            return 130
        segments = session.segments
        console.print(
            f"arm time {session.arm_seconds:.1f} s excitation + ~{session.move_seconds:.1f} s moves"
        )
    outcome, replay = fit(
        segments, console, args.window, args.iterations, fit_starts=not args.no_fit_starts
    )
    meta = fit_metadata(outcome, session, args.window, log_path)
    save_arm_params(outcome.params, out, extra={"_fit": meta})
    console.print(f"wrote {out}")
    for key, q in outcome.fitted_quality.items():
        nom = outcome.nominal_quality[key]["window"]
        console.print(
            f"{key}: R^2 {q['window']['r2']:.4f} RMS {q['window']['rms_mrad']:.2f} mrad "
            f"(nominal twin {nom['r2']:.4f}, {nom['rms_mrad']:.2f} mrad)"
        )
    gap_text = None
    if args.check_controller:
        if truth is None:
            console.print("[red]error:[/] --check-controller needs --truth (the hidden arm)")
            return 2
        gap_text, gap_summary = check_controllers(
            args.check_controller.split(","), truth, outcome.params, args.check_episodes, console
        )
        meta["controller_gap"] = gap_summary
        save_arm_params(outcome.params, out, extra={"_fit": meta})
    if not args.no_report:
        path = write_report(outcome, replay, segments, report_dir, args.window, session, truth)
        if gap_text is not None:
            with path.open("a", encoding="utf-8") as f:
                f.write("\n" + gap_text)
        console.print(f"report {path}")
    return 0


def check_controllers(
    names: Sequence[str], truth: ArmParams, fitted: ArmParams, episodes: int, console: Console
) -> tuple[str, list[dict[str, Any]]]:
    """tools/twin_gap.py on the fit: its markdown and per-controller summary."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "twin_gap", Path(__file__).resolve().parent / "twin_gap.py"
    )
    if spec is None or spec.loader is None:
        raise RuntimeError("tools/twin_gap.py not found beside identify.py")
    gap = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = gap
    spec.loader.exec_module(gap)
    from policy.campaigns.evaluation import random_episodes

    gaps = gap.measure_gap(
        [n.strip() for n in names if n.strip()], truth, fitted, random_episodes(episodes, 0)
    )
    for g in gaps:
        f, n = g.summary()["fitted"], g.summary()["nominal"]
        console.print(
            f"{g.controller}: energy error fitted {100 * f['energy_error_max']:.2f} % "
            f"(nominal {100 * n['energy_error_max']:.2f} %), settling error fitted "
            f"{f['settling_error_max_s']:.3f} s (nominal {n['settling_error_max_s']:.3f} s), "
            f"worst of {len(g.episodes)} episodes; targets "
            f"{'met' if f['meets_targets'] else 'NOT met'}"
        )
    return gap.markdown(gaps), [g.summary() for g in gaps]


if __name__ == "__main__":
    sys.exit(main())
