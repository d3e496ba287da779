"""The hardware status flags each device last reported, and which of them must stop a joint."""

from __future__ import annotations

import threading

from protocol import HardwareStatus, Packet, ProtocolError
from reach_driver.link import EventKind
from reach_driver.state import joint_name

#: Flags that only say the arm saw noise on the line; they clear by themselves.
LINK_ERROR_FLAGS = HardwareStatus.SERIAL_ERROR | HardwareStatus.CRC_ERROR


class FaultFlags:
    """Fed HARDWARE_STATUS packets by the reader thread; read from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._flags: dict[int, HardwareStatus] = {}

    def note(self, packet: Packet) -> tuple[EventKind, str, int] | None:
        """Record a status packet; the event to report when a device's flags changed."""
        try:
            flags = HardwareStatus.from_bytes(packet.data)
        except ProtocolError:
            return None
        dev = int(packet.device_id)
        with self._lock:
            before = self._flags.get(dev, HardwareStatus.NONE)
            if flags == before:
                return None
            self._flags[dev] = flags
        if flags:
            names = ", ".join(flags.flag_names()) or f"0x{int(flags):08X}"
            return EventKind.FAULT, f"{joint_name(dev)} reports {names}", dev
        return EventKind.FAULT_CLEARED, f"{joint_name(dev)} status clear", dev

    def blocking(self) -> dict[int, list[str]]:
        """Flags, by device, that say a joint must not be driven (link error flags left out)."""
        with self._lock:
            faults = dict(self._flags)
        out: dict[int, list[str]] = {}
        for dev, flags in faults.items():
            serious = flags & ~LINK_ERROR_FLAGS
            if serious:
                out[dev] = serious.flag_names() or [f"0x{int(serious):08X}"]
        return out
