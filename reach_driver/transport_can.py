"""The BPL byte stream tunnelled over CAN, for arms behind a CAN gateway (docs/can-tunnel.md).

URL: `can://INTERFACE/CHANNEL[?tx=0x1A0&rx=0x1A1&fd=0&extended=0&OPTION=VALUE...]`, where
INTERFACE/CHANNEL are python-can's (`virtual/ch0`, `socketcan/can0`, `pcan/PCAN_USBBUS1`) and
any other option (bitrate, ...) goes to `can.Bus`. Each CAN frame carries a sequence byte and
up to 7 (CAN FD: 63) bytes of the stream; the stream's own 0x00 delimiters mark BPL frames, so
no other segmentation is needed and a lost CAN frame costs exactly the BPL frames it touched.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar
from urllib.parse import parse_qsl, urlsplit

import can

from reach_driver.errors import BadUrlError, TransportError
from reach_driver.transport import DEFAULT_READ_TIMEOUT_S, Transport

HOST_TO_ARM_ID = 0x1A0
ARM_TO_HOST_ID = 0x1A1
CLASSIC_PAYLOAD = 7  # 8 data bytes minus the sequence byte
FD_PAYLOAD = 63  # 64 data bytes minus the sequence byte
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
MAX_DRAIN = 64  # CAN frames gathered into one read() when they are already queued


@dataclass(frozen=True)
class CanTunnelConfig:
    """Which CAN ids carry each direction; the gateway uses the same config with them swapped."""

    tx_id: int = HOST_TO_ARM_ID
    rx_id: int = ARM_TO_HOST_ID
    extended: bool = False
    fd: bool = False

    def __post_init__(self) -> None:
        limit = 0x1FFFFFFF if self.extended else 0x7FF
        for name, value in (("tx", self.tx_id), ("rx", self.rx_id)):
            if not 0 <= value <= limit:
                kind = "29-bit" if self.extended else "11-bit"
                raise BadUrlError(f"CAN id {name}=0x{value:X} does not fit a {kind} identifier")
        if self.tx_id == self.rx_id:
            raise BadUrlError(f"tx and rx must be different CAN ids (both 0x{self.tx_id:X})")

    def swapped(self) -> CanTunnelConfig:
        """The other end's view of the tunnel."""
        return CanTunnelConfig(self.rx_id, self.tx_id, self.extended, self.fd)


class TunnelFramer:
    """Cuts stream bytes into CAN payloads `[seq, bytes...]`, seq counting 0..255 and wrapping."""

    def __init__(self, fd: bool = False) -> None:
        self.fd = fd
        self._seq = 0

    def payloads(self, data: bytes) -> list[bytes]:
        size = FD_PAYLOAD if self.fd else CLASSIC_PAYLOAD
        out = []
        for start in range(0, len(data), size):
            chunk = data[start : start + size]
            payload = bytes([self._seq]) + chunk
            if self.fd and len(payload) not in FD_LENGTHS:
                # Only the last chunk of a write can be short; writes end on a frame's 0x00
                # delimiter, so 0x00 padding is just empty pieces to the decoder.
                padded = next(n for n in FD_LENGTHS if n >= len(payload))
                payload += bytes(padded - len(payload))
            out.append(payload)
            self._seq = (self._seq + 1) & 0xFF
        return out


class TunnelDeframer:
    """Rebuilds the stream; a sequence gap is counted and closed with a 0x00 so the decoder
    drops the damaged BPL frame instead of gluing it to the next one."""

    def __init__(self) -> None:
        self._expected: int | None = None
        self.lost = 0

    def accept(self, payload: bytes) -> bytes:
        if not payload:
            return b""
        seq, body = payload[0], bytes(payload[1:])
        expected, self._expected = self._expected, (seq + 1) & 0xFF
        if expected is not None and seq != expected:
            self.lost += (seq - expected) & 0xFF
            return b"\x00" + body
        return body


def parse_can_url(url: str) -> tuple[str, str, CanTunnelConfig, dict[str, Any]]:
    """`can://virtual/ch0?tx=0x1A0` -> (interface, channel, tunnel config, extra bus kwargs)."""
    parts = urlsplit(url)
    interface = parts.netloc
    channel = parts.path.lstrip("/")
    if not interface or not channel:
        raise BadUrlError(
            f"expected can://INTERFACE/CHANNEL (e.g. can://socketcan/can0), got {url!r}"
        )
    options: dict[str, str] = dict(parse_qsl(parts.query, keep_blank_values=True))

    def number(key: str, default: int) -> int:
        text = options.pop(key, None)
        if text is None:
            return default
        try:
            return int(text, 0)
        except ValueError:
            raise BadUrlError(f"{key}={text!r} in {url!r} is not an integer") from None

    def flag(key: str) -> bool:
        text = options.pop(key, "0").lower()
        if text not in ("0", "1", "true", "false", "yes", "no"):
            raise BadUrlError(f"{key}={text!r} in {url!r}: use 0 or 1")
        return text in ("1", "true", "yes")

    config = CanTunnelConfig(
        tx_id=number("tx", HOST_TO_ARM_ID),
        rx_id=number("rx", ARM_TO_HOST_ID),
        extended=flag("extended"),
        fd=flag("fd"),
    )
    extra: dict[str, Any] = {}
    for key, text in options.items():
        try:
            extra[key] = int(text, 0)
        except ValueError:
            extra[key] = text
    return interface, channel, config, extra


class CanTransport(Transport):
    """One end of the CAN tunnel; the host end by default, the gateway end with `swapped()`."""

    link_errors: ClassVar[tuple[type[BaseException], ...]] = (can.CanError,)
    # A byte stream: a host that died mid-write left part of a frame in the gateway's path,
    # and a restarted sequence only sometimes shows as a gap (which would close it).
    opens_with_delimiter: ClassVar[bool] = True
    read_failed: ClassVar[str] = "CAN receive on"
    write_failed: ClassVar[str] = "CAN send on"

    def __init__(
        self,
        interface: str,
        channel: str,
        config: CanTunnelConfig | None = None,
        *,
        bus_kwargs: Mapping[str, Any] | None = None,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        url: str | None = None,
    ) -> None:
        super().__init__(url or f"can://{interface}/{channel}", read_timeout_s)
        self.interface = interface
        self.channel = channel
        self.config = config or CanTunnelConfig()
        self.bus_kwargs = dict(bus_kwargs or {})
        self._bus: can.BusABC | None = None
        self._framer = TunnelFramer(self.config.fd)
        self._deframer = TunnelDeframer()

    @classmethod
    def from_url(cls, url: str, read_timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> CanTransport:
        interface, channel, config, extra = parse_can_url(url)
        return cls(
            interface, channel, config, bus_kwargs=extra, read_timeout_s=read_timeout_s, url=url
        )

    @property
    def is_open(self) -> bool:
        return self._bus is not None

    def _open_internal(self) -> None:
        kwargs = dict(self.bus_kwargs)
        if self.config.fd:
            kwargs["fd"] = True
        try:
            bus = can.Bus(interface=self.interface, channel=self.channel, **kwargs)
        except (can.CanError, ValueError, OSError, ImportError) as exc:
            raise TransportError(f"cannot open CAN bus {self.url}: {exc}") from None
        mask = 0x1FFFFFFF if self.config.extended else 0x7FF
        bus.set_filters(
            [{"can_id": self.config.rx_id, "can_mask": mask, "extended": self.config.extended}]
        )
        self._bus = bus
        self._framer = TunnelFramer(self.config.fd)
        self._deframer = TunnelDeframer()

    def close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def _require(self) -> can.BusABC:
        if self._bus is None:
            raise TransportError(f"{self.url} is not open")
        return self._bus

    def _read_internal(self) -> bytes:
        bus = self._require()
        out = bytearray()
        timeout: float = self.read_timeout_s
        for _ in range(MAX_DRAIN):
            msg = bus.recv(timeout=timeout)
            if msg is None:
                break
            timeout = 0.0  # after the first frame take only what is already queued
            if msg.arbitration_id != self.config.rx_id or msg.is_error_frame:
                continue
            before = self._deframer.lost
            out += self._deframer.accept(bytes(msg.data))
            self.stats.lost_can_frames += self._deframer.lost - before
        return bytes(out)

    def _write_internal(self, piece: bytes) -> None:
        bus = self._require()
        for payload in self._framer.payloads(piece):
            bus.send(
                can.Message(
                    arbitration_id=self.config.tx_id,
                    data=payload,
                    is_extended_id=self.config.extended,
                    is_fd=self.config.fd,
                ),
                timeout=1.0,
            )
