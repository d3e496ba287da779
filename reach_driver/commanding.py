"""What the client sends the arm to command it: packets through the gate, the motion helpers
(joint positions, velocities, currents, a tool position by the driver's inverse kinematics)
and the safe mode, confirmed by reading the modes back (`make_safe`).

`ArmCommands` is a part of `ArmClient` (`reach_driver.client`), kept apart because it is the
client's command side: every write here that can move the arm passes the gate
(`reach_driver.gate`) and tells the watchdog which joints it arms. It runs on the caller's
thread; it builds on the reads of `ArmQueries` (`solve_xyz` polls the joints, `make_safe`
reads the modes back). The state it uses is the client's, declared below.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from protocol import Mode, Packet, PacketID, ProtocolError, commands, decode_packet
from protocol.models import ALPHA5, model_named
from reach_driver import ik
from reach_driver.drawing import DRAWINGS
from reach_driver.errors import DriverError, LimitError
from reach_driver.link import LinkState
from reach_driver.queries import ArmQueries
from reach_driver.safe_stop import SafeStop
from reach_driver.state import joint_name
from reach_driver.supervisor import LinkSupervisor
from reach_driver.watchdog import Watchdog

SAFE_RETRY_S = 0.05
"""`make_safe`: the pause between attempts (a silent arm already costs each attempt its
request timeouts)."""


class ArmCommands(ArmQueries):
    """Commands of `ArmClient` (see the module docstring)."""

    watchdog: Watchdog
    supervisor: LinkSupervisor

    def send(self, *packets: Packet) -> None:
        """Write packets as they are, after the same safety checks as the command helpers.

        Every packet passes the gate (`reach_driver.gate`): only packets known to be
        harmless, and checked motion and limit writes, go out; one refusal sends nothing.
        """
        for p in packets:
            self._gate.check_packet(p)
        self._write_commands(packets)

    def send_unchecked(self, *packets: Packet) -> None:
        """Write packets with no safety check at all (bench work, protocol tests). Nothing
        in the CLI uses it."""
        self._write_commands(packets)

    def write_frames(self, frames: Sequence[bytes]) -> float:
        """Encoded frames, each decoded and passed through the same gate as `send`; returns
        the write completion time. Joints they arm are armed in the watchdog, but nothing
        here disarms one (tests use it to fake feedback on loop://)."""
        packets = []
        for frame in frames:
            try:
                packets.append(decode_packet(frame))
            except ProtocolError as exc:
                raise LimitError(
                    f"refused: a frame that does not decode ({exc}) cannot be checked; "
                    "write_frames_unchecked() writes it as it is; nothing was sent"
                ) from None
        for p in packets:
            self._gate.check_packet(p)
        return self._write_commands(packets, disarm=False)

    def write_frames_unchecked(self, frames: Sequence[bytes]) -> float:
        """Raw frames with no check at all (malformed-frame tests, tools); returns the write
        completion time. Nothing in the CLI uses it."""
        return self._write(frames)

    def set_mode(self, devices: int | Sequence[int], mode: Mode) -> None:
        devs = [devices] if isinstance(devices, int) else list(devices)
        self.send(*(commands.mode(int(d), mode) for d in devs))

    def command_position(self, device: int, value: float) -> None:
        """Absolute position (rad; mm for the jaw); refused outside the position limit."""
        self._positions([int(device)], [float(value)])

    def command_positions(self, q: Sequence[float] | np.ndarray) -> None:
        """Positions of every joint in the model's order (E D C B on the Alpha 5); all are
        checked before any is sent."""
        self._positions(self.model.joints, self._per_joint(q))

    def _per_joint(self, values: Sequence[float] | np.ndarray) -> list[float]:
        """One float per joint of the model, in its order (ValueError naming the order)."""
        out = [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]
        if len(out) != self.model.n_joints:
            order = " ".join(self.model.joint_letters)
            raise ValueError(
                f"expected {self.model.n_joints} values in joint order {order}, got {len(out)}"
            )
        return out

    def _positions(self, devices: Sequence[int], values: Sequence[float]) -> None:
        self._gate.check_positions(devices, values)
        self.send(*(commands.position(int(d), v) for d, v in zip(devices, values, strict=True)))

    def solve_xyz(self, x: float, y: float, z: float) -> np.ndarray:
        """Joint target (rad, the model's order) putting the tool centre point at (x, y, z)
        mm in the base frame, from the present angles, inside the position limits in force
        (the arm's, tightened by the safety config); B keeps its angle (it does not move the
        tool centre point). Sends nothing; `ik.UnreachableError` (a `LimitError`) if no
        angles inside the limits get within `ik.TOLERANCE_MM`. The Alpha 5 by `ik`'s solver,
        another model on its chain from its MJCF (`ik.solve_on_chain`: the Bravo 7's G F E D
        C move, redundantly, the least from where they are); a model the driver has no
        chain for gets a `LimitError` saying so."""
        if self.model.name not in DRAWINGS:
            known = " and the ".join(f"{model_named(name).title}'s" for name in DRAWINGS)
            raise LimitError(
                f"refused: the driver's inverse kinematics are the {known}, not the "
                f"{self.model.title}'s; command joint angles instead; nothing was sent"
            )
        q = self.state.q
        if not np.all(np.isfinite(q)):
            q = self.read_joints((PacketID.POSITION,)).q
        limits = np.array(self.guard.position_limits())
        if self.model is ALPHA5:
            return ik.solve_or_refuse((x, y, z), q, limits)
        drawing = DRAWINGS[self.model.name]
        letters = self.model.joint_letters
        return ik.solve_on_chain_or_refuse(drawing, letters, (x, y, z), q, limits)

    def command_xyz(self, x: float, y: float, z: float) -> np.ndarray:
        """Move the tool centre point to (x, y, z) mm: the driver's own inverse kinematics
        (`solve_xyz`), then joint POSITION commands through the same gate as
        `command_positions` (limits, blocking faults); never a raw KM_END_POS. Returns the
        joint target sent."""
        q = self.solve_xyz(x, y, z)
        self.command_positions(q)
        return q

    def command_jaw(self, mm: float) -> None:
        self.command_position(self.model.jaw, mm)

    def command_velocity(self, device: int, value: float) -> float:
        return float(self.command_velocities_for([int(device)], [value])[0])

    def command_velocities(self, v: Sequence[float] | np.ndarray) -> np.ndarray:
        """Velocities of every joint in the model's order, after the soft barrier (what was
        actually sent)."""
        return self.command_velocities_for(self.model.joints, self._per_joint(v))

    def command_velocities_for(
        self, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> np.ndarray:
        return self._continuous(PacketID.VELOCITY, devices, values)

    def command_current(self, device: int, milliamps: float) -> float:
        return float(self._continuous(PacketID.CURRENT, [int(device)], [milliamps])[0])

    def command_currents(self, currents_mA: Sequence[float] | np.ndarray) -> np.ndarray:
        """Currents of every joint in the model's order in mA, after the soft barrier (what
        was actually sent)."""
        return self._continuous(PacketID.CURRENT, self.model.joints, self._per_joint(currents_mA))

    def _continuous(
        self, pid: PacketID, devices: Sequence[int], values: Sequence[float] | np.ndarray
    ) -> np.ndarray:
        devs, sent = self._gate.continuous(pid, devices, values)
        builder = commands.current if pid is PacketID.CURRENT else commands.velocity
        self._write_commands([builder(d, float(v)) for d, v in zip(devs, sent, strict=True)])
        return sent

    def _write_commands(self, packets: Sequence[Packet], *, disarm: bool = True) -> float:
        """Write checked commands; the watchdog learns which joints they arm (or disarm)."""
        done = self._write([p.encode() for p in packets])
        self.watchdog.note_sent(packets, self.clock(), disarm=disarm)
        return done

    def safe_stop(self, devices: Sequence[int] | None = None) -> None:
        """Put joints (default: the four joints and the jaw) in the configured safe mode."""
        self._send_safe_mode(tuple(devices or self.model.actuators))

    def make_safe(
        self, devices: Sequence[int] | None = None, *, wait_s: float | None = None
    ) -> SafeStop:
        """Put `devices` (default: the four joints and the jaw) in the safe mode and read
        their modes back; until all confirm it, send it again, for up to `wait_s` wall
        seconds (default `SafetyConfig.safe_wait_s`), waiting for a lost link meanwhile.
        Unconfirmed, the safe mode stays owed: this client sends it once the link is back."""
        devs = tuple(int(d) for d in (devices or self.model.actuators))
        mode = self.guard.config.safe_mode
        wait = self.guard.config.safe_wait_s if wait_s is None else float(wait_s)
        start = time.monotonic()
        deadline = start + wait
        sent = 0
        problem = ""
        saw_down = False
        while True:
            state = self.supervisor.state
            if state is LinkState.UP:
                try:
                    self._send_safe_mode(devs)
                    sent += 1
                    problem = self.mode_problem(devs, mode)
                except DriverError as exc:
                    problem = str(exc)
                else:
                    if not problem:
                        return SafeStop(mode, True, sent, time.monotonic() - start, wait, saw_down)
            else:
                saw_down = True
                problem = problem or f"link {state.value}: {self.supervisor.reason}"
                if state in (LinkState.CLOSED, LinkState.FAILED):
                    break
            if time.monotonic() >= deadline:
                break
            time.sleep(SAFE_RETRY_S)
        self.watchdog.mark_safe_pending()
        state = self.supervisor.state
        down = None if state is LinkState.UP else f"{state.value} ({self.supervisor.reason})"
        return SafeStop(mode, False, sent, time.monotonic() - start, wait, saw_down, problem, down)

    def mode_problem(self, devices: Sequence[int], mode: Mode) -> str:
        """Read the modes of `devices` back: "" when every one answers `mode`, else what
        differs ("no answer from E D, C in current")."""
        modes = self.read_modes(devices)
        silent = [joint_name(d) for d, m in modes.items() if m is None]
        other = [
            f"{joint_name(d)} in {_mode_name(m)}" for d, m in modes.items() if m not in (None, mode)
        ]
        parts = ([f"no answer from {' '.join(silent)}"] if silent else []) + other
        return ", ".join(parts)

    def rearm(self) -> None:
        """Allow velocity/current commands again after a watchdog trip."""
        self.watchdog.rearm()

    def _send_safe_mode(self, devices: Sequence[int]) -> None:
        self._write(self._safe_mode_frames(devices))
        self.watchdog.disarm(devices)

    def _safe_mode_frames(self, devices: Sequence[int]) -> list[bytes]:
        mode = self.guard.config.safe_mode
        return [commands.mode(int(d), mode).encode() for d in devices]


def _mode_name(mode: Mode | int | None) -> str:
    return mode.name.lower() if isinstance(mode, Mode) else f"mode 0x{int(mode or 0):02X}"
