"""Which arm this is: what each device reported at connect (serial and model numbers,
firmware version), and the check after a reconnect that the same arm answers.

A reconnect reopens a path (a pty, a serial adapter, a UDP address) that another arm can sit
behind by then. Re-applying the old set-up to it, or accepting its positions as this arm's,
would drive or report the wrong machine, so the client confirms the identity first.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

from protocol import Packet, PacketID, ProtocolError, commands
from reach_driver.state import joint_name, packet_value

#: What identifies a device, and the JointState/DeviceIdentity field each fills.
IDENTITY_FIELDS: dict[int, str] = {
    PacketID.SERIAL_NUMBER: "serial_number",
    PacketID.MODEL_NUMBER: "model_number",
    PacketID.SOFTWARE_VERSION: "software_version",
}
IDENTITY_PACKETS: tuple[int, ...] = tuple(IDENTITY_FIELDS)


@dataclass(frozen=True)
class DeviceIdentity:
    """One device's identity; None for what it did not report at connect (not checked)."""

    serial_number: float | None = None
    model_number: float | None = None
    software_version: str | None = None

    @classmethod
    def from_replies(cls, replies: Mapping[int, Packet]) -> DeviceIdentity:
        values: dict[str, object] = {}
        for pid, name in IDENTITY_FIELDS.items():
            packet = replies.get(pid)
            if packet is not None:
                try:
                    values[name] = packet_value(packet)
                except ProtocolError:
                    pass
        return cls(**values)  # type: ignore[arg-type]

    def known(self) -> dict[str, object]:
        return {
            f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None
        }


def field_label(name: str) -> str:
    return name.replace("_", " ")


class IdentityCheck:
    """Collects a reopened link's identity replies (reader thread) and compares them."""

    def __init__(self, expected: Mapping[int, DeviceIdentity]) -> None:
        self.expected = dict(expected)
        self.wanted: set[tuple[int, int]] = {
            (dev, pid)
            for dev, ident in self.expected.items()
            for pid, name in IDENTITY_FIELDS.items()
            if getattr(ident, name) is not None
        }
        self.differences: list[str] = []

    def frames(self) -> list[bytes]:
        out = []
        for dev in sorted(self.expected, reverse=True):
            ids = [pid for pid in IDENTITY_PACKETS if (dev, pid) in self.wanted]
            if ids:
                out.append(commands.request(dev, ids).encode())
        return out

    @property
    def complete(self) -> bool:
        return not self.wanted

    def offer(self, packet: Packet) -> None:
        key = (int(packet.device_id), int(packet.packet_id))
        if key not in self.wanted:
            return
        self.wanted.discard(key)
        dev, pid = key
        name = IDENTITY_FIELDS[pid]
        was = getattr(self.expected[dev], name)
        try:
            now = packet_value(packet)
        except ProtocolError:
            now = f"malformed {packet.data.hex()}"
        if now != was:
            self.differences.append(
                f"{joint_name(dev)} {field_label(name)} {_show(now)} (was {_show(was)})"
            )


def _show(value: object) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)
