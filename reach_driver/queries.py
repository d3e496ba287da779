"""What the client asks the arm: matched requests and the reads built on them (which devices
answer, their identity, limits, versions, Monitor readings, modes, status flags, joints).

`ArmQueries` is a part of `ArmClient` (`reach_driver.client`), kept apart because it is the
client's request side: it asks (for limits, writes and reads back) and adopts what comes
back; it never commands motion and never runs on the reader thread. The state it uses is the
client's, declared below.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from protocol import Mode, Packet, PacketDecoder, PacketID, ProtocolError, commands
from protocol.models import ALPHA5, ArmModel, Range
from reach_driver.errors import GarbageError, LimitError, NoResponseError
from reach_driver.gate import CommandGate
from reach_driver.identity import IDENTITY_PACKETS, DeviceIdentity
from reach_driver.requests import Replies, Requester
from reach_driver.safety import LimitKind, SafetyGuard, as_range, envelope_problem
from reach_driver.state import ArmState, JointState, StateTable, joint_name, packet_value
from reach_driver.transport import Transport

#: What `read_diagnostics` asks each device for (docs/protocol.md section 3a).
DIAGNOSTICS = (
    PacketID.VOLTAGE,
    PacketID.INTERNAL_TEMPERATURE,
    PacketID.INTERNAL_HUMIDITY,
    PacketID.INTERNAL_PRESSURE,  # 0x67 as V1.12.1 has it (newer SDKs: DEVICE_TYPE)
    PacketID.PRESSURE,  # 0x6E, the newer SDKs' pressure
    PacketID.FACTORY_CLIMATE,
    PacketID.HARDWARE_STATUS,
)


class ArmQueries:
    """Requests and reads of `ArmClient` (see the module docstring)."""

    transport: Transport
    model: ArmModel
    guard: SafetyGuard
    devices: tuple[int, ...]
    request_timeout_s: float
    retries: int
    clock: Callable[[], float]
    table: StateTable
    decoder: PacketDecoder
    found_devices: tuple[int, ...]
    identity: dict[int, DeviceIdentity]
    warnings: list[str]
    _requests: Requester
    _gate: CommandGate

    if TYPE_CHECKING:

        @property
        def state(self) -> ArmState: ...

        def _write(self, frames: Sequence[bytes], *, internal: bool = False) -> float: ...

    # ----------------------------------------------------------------- requests

    def request(
        self,
        device: int,
        ids: Sequence[int],
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> dict[int, Packet]:
        """Ask one device for packets; returns {packet id: reply}.

        Replies are matched by device *and* packet id. Missing ones are asked for again up
        to `retries` times; then `RequestTimeoutError` names what never came.
        """
        got = self.request_many([device], ids, timeout_s=timeout_s, retries=retries)
        return got[int(device)]

    def request_many(
        self,
        devices: Sequence[int],
        ids: Sequence[int],
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
        partial: bool = False,
    ) -> Replies:
        """The same packet ids from several devices, all requests written at once (one
        device at a time on a half-duplex bus).

        With `partial=True` devices that never answer are left out instead of raising.
        """
        return self._requests.request_many(
            devices,
            ids,
            timeout_s=self.request_timeout_s if timeout_s is None else timeout_s,
            retries=self.retries if retries is None else retries,
            partial=partial,
        )

    # ----------------------------------------------------------------- discovery and info

    def discover(self, devices: Sequence[int] | None = None) -> tuple[int, ...]:
        """Find which devices answer (a MODE request each); raises if none does."""
        devs = list(devices or self.devices)
        before = self.decoder.stats.good_frames, self.decoder.stats.bytes_received
        got = self.request_many(devs, [PacketID.MODE], partial=True)
        self.found_devices = tuple(d for d in devs if d in got)
        if not self.found_devices:
            stats = self.decoder.stats
            received = stats.bytes_received - before[1]
            waited = self.request_timeout_s * (1 + self.retries)
            baud = getattr(self.transport, "baud", None)
            if received and stats.good_frames == before[0]:
                raise GarbageError(
                    f"{received} bytes arrived on {self.transport.url} in {waited:.2g} s but "
                    f"none decoded as a BPL frame ({stats.bad_total} bad frames)"
                    + (f": wrong baud rate? (using {baud})" if baud else "")
                )
            raise NoResponseError(
                f"nothing answered on {self.transport.url} within {waited:.2g} s "
                f"(asked devices {', '.join(joint_name(d) for d in devs)}): is the arm powered "
                "and is this its port or address?"
            )
        return self.found_devices

    def read_identity(self, devices: Sequence[int] | None = None) -> dict[int, DeviceIdentity]:
        """Serial and model numbers and firmware version of each device that answers; kept
        in `identity` to confirm the same arm answers after a reconnect."""
        devs = list(devices or self.found_devices or self.devices)
        got = self.request_many(devs, IDENTITY_PACKETS, partial=True)
        for d in devs:
            if got.get(d):
                self.identity[d] = DeviceIdentity.from_replies(got[d])
        return dict(self.identity)

    def read_limits(
        self, devices: Sequence[int] | None = None
    ) -> dict[int, dict[LimitKind, Range]]:
        """Read position, velocity and current limits; the safety guard adopts the plausible
        ones (finite, inside the factory envelope) and returns those.

        A device that does not report a limit, or reports one that is not plausible, keeps
        the one in force (the documented default at first) and a warning is recorded in
        `warnings`.
        """
        devs = list(devices or self.found_devices or self.devices)
        kinds = list(LimitKind)
        for d in devs:
            for kind in kinds:
                self.table.forget(d, kind.packet_id)
        got = self.request_many(devs, [k.packet_id for k in kinds], partial=True)
        out: dict[int, dict[LimitKind, Range]] = {}
        for d in devs:
            for kind in kinds:
                reply = got.get(d, {}).get(kind.packet_id)
                value, problem = limit_verdict(reply, d, kind, self.model)
                if value is not None and problem is None:  # adopted as it arrived
                    out.setdefault(d, {})[kind] = as_range(kind, value)
                elif reply is not None or not self.guard.has_arm_limit(d, kind):
                    said = "did not report its" if reply is None else "reported implausible"
                    self.warnings.append(
                        f"{joint_name(d)} {said} {kind.value} limits"
                        + (f" ({problem})" if reply is not None else "")
                        + "; keeping the ones in force"
                    )
        return out

    def write_limits(self, device: int, kind: LimitKind, maximum: float, minimum: float) -> Range:
        """Tighten one limit on the arm, read it back and adopt what the arm reports.

        Refused (`LimitError`, nothing sent) unless finite, inside the factory envelope and
        inside the present limit; `widen_limits` is the call that may widen it.
        """
        return self._set_limits(int(device), kind, maximum, minimum, widen=False)

    def widen_limits(self, device: int, kind: LimitKind, maximum: float, minimum: float) -> Range:
        """Like `write_limits`, but may widen the present limit (never past the factory
        envelope, never to a non-finite value)."""
        return self._set_limits(int(device), kind, maximum, minimum, widen=True)

    def _set_limits(
        self, device: int, kind: LimitKind, maximum: float, minimum: float, *, widen: bool
    ) -> Range:
        self._gate.check_limit_write(device, kind, (maximum, minimum), widen=widen)
        self._write([commands.limits(int(device), kind.packet_id, maximum, minimum).encode()])
        self.table.forget(int(device), kind.packet_id)
        reply = self.request(device, [kind.packet_id])[kind.packet_id]
        value, problem = limit_verdict(reply, device, kind, self.model)
        if value is None or problem is not None:
            raise LimitError(
                f"{joint_name(device)} answered the {kind.value} limit write with "
                f"{problem or 'a malformed payload'}; not adopted, the old limit stays"
            )
        return as_range(kind, value)

    def read_info(self, devices: Sequence[int] | None = None) -> dict[int, JointState]:
        """Versions, serial and model numbers, modes and status flags of each device."""
        devs = list(devices or self.found_devices or self.devices)
        ids = [
            PacketID.MODE,
            PacketID.SOFTWARE_VERSION,
            PacketID.SERIAL_NUMBER,
            PacketID.MODEL_NUMBER,
            PacketID.HARDWARE_STATUS,
        ]
        self.request_many(devs, ids, partial=True)
        return {d: self.table.get(d) for d in devs}

    def read_diagnostics(self, devices: Sequence[int] | None = None) -> dict[int, JointState]:
        """The Monitor readings of each device (supply voltage, internal temperature,
        humidity and pressure, the factory climate) and its status flags; a device or value
        that does not answer is left as it was (None if never read)."""
        devs = list(devices or self.found_devices or self.devices)
        self.request_many(devs, DIAGNOSTICS, partial=True)
        return {d: self.table.get(d) for d in devs}

    def read_modes(self, devices: Sequence[int] | None = None) -> dict[int, Mode | int | None]:
        """Each device's mode as it answers now (None if it did not answer). Replies come
        after every frame written before the request, so this confirms a mode change."""
        devs = list(devices or self.found_devices or self.devices)
        asked = self.clock()
        self.request_many(devs, [PacketID.MODE], partial=True)
        out: dict[int, Mode | int | None] = {}
        for d in devs:
            reading = self.table.get(d).mode
            out[d] = None if reading is None or reading.t < asked else reading.value
        return out

    def read_status(self, devices: Sequence[int] | None = None) -> dict[int, list[str]]:
        """Hardware status flags by name for each device that answers ([] when healthy)."""
        devs = list(devices or self.found_devices or self.devices)
        self.request_many(devs, [PacketID.HARDWARE_STATUS], partial=True)
        out = {}
        for d in devs:
            js = self.table.get(d)
            if js.status is not None:
                out[d] = js.fault_names
        return out

    def read_joints(self, ids: Sequence[int] = (PacketID.POSITION, PacketID.VELOCITY)) -> ArmState:
        """Poll the joints once (one write) and return the fresh state."""
        self.request_many(self.model.joints, ids)
        return self.state


def limit_verdict(
    packet: Packet | None, device: int, kind: LimitKind, model: ArmModel = ALPHA5
) -> tuple[Range | None, str | None]:
    """(the limits a packet carries, why they are not plausible or None); (None, None) for
    no packet or a malformed one."""
    if packet is None:
        return None, None
    try:
        value = packet_value(packet)
    except ProtocolError:
        return None, None
    assert isinstance(value, tuple)
    return value, envelope_problem(device, kind, value, model)
