"""Running the excitation on an arm through `reach_driver`: position-mode moves to each pose
(`move_to`) and each wave of each joint in current mode (`excite`), collected in a `Session`."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from policy.campaigns.identification.recording import ExcitationRecorder, StepStamps
from policy.controllers.excitation import HOME, Amplitudes, Excitation, Wave, pose
from protocol import Mode, PacketID
from protocol.alpha5 import JOINT_LETTERS, JOINTS
from reach_driver import ArmClient, ControlLoop, DriverError
from reach_driver.errors import NoResponseError, RequestTimeoutError
from reach_sim_bridge.fit.segments import Segment, segment_suffix
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams

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
class Session:
    segments: list[Segment] = field(default_factory=list)
    arm_seconds: float = 0.0  # in current mode, exact (ticks)
    move_seconds: float = 0.0  # in moves, wall x the measured arm speed
    arm_speed: float = 1.0
    retries: int = 0  # segments run again after a watchdog trip (a stalled host)


def excite(
    client: ArmClient,
    joints: Sequence[int],
    waves: Sequence[Wave],
    rate_hz: float,
    console: Console,
    session: Session,
    max_current: np.ndarray,
    recorder: ExcitationRecorder | None = None,
    payload: tuple[float, float] = (0.0, 0.0),
) -> None:
    """Run every wave on every joint, appending to `session` (and `recorder`) as segments
    finish. `payload`: the known load (kg, litres) the arm holds in its jaws throughout; the
    segments are tagged with it and the hold's gravity feed-forward counts it."""
    period = 1.0 / rate_hz
    kg, litres = payload
    twin = Alpha5Arm(ArmParams(payload_kg=kg, payload_volume_l=litres))
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
                    name=f"{letter}{k}-{wave.kind}-{wave.pose}{segment_suffix(kg)}",
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
                    payload_kg=kg,
                    payload_volume_l=litres,
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
