"""One byte-stream interface for every link to the arm, chosen by a URL string.

Like pyserial's `serial_for_url` and python-can's interface names: the rest of the driver
never knows whether bytes travel over a tty, UDP datagrams or a CAN tunnel.

    open_transport("/dev/ttyUSB0")                # serial, 115200 8N1
    open_transport("/dev/ttyUSB0", rs485=True)   # half duplex: writes spaced, no broadcast
    open_transport("loop://")                     # any pyserial URL
    open_transport("udp://192.168.2.3")           # port 6789 by default
    open_transport("can://virtual/ch0")           # python-can interface/channel, see can-tunnel.md
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

from reach_driver.errors import BadUrlError

DEFAULT_BAUD = 115200
DEFAULT_UDP_PORT = 6789
DEFAULT_READ_TIMEOUT_S = 0.01


@dataclass
class TransportStats:
    """Counters a transport keeps about its link (read by the monitor; reset on demand)."""

    bytes_in: int = 0
    bytes_out: int = 0
    writes: int = 0
    opens: int = 0
    read_errors: int = 0
    write_errors: int = 0
    foreign_datagrams: int = 0  # UDP datagrams from a source other than the arm
    lost_can_frames: int = 0  # gaps in the CAN tunnel's sequence numbers


class Transport(abc.ABC):
    """A link carrying the BPL byte stream both ways.

    `read()` waits at most `read_timeout_s` and returns b"" when nothing came, so one thread
    can read and still run periodic duties. `write()` takes whole encoded frames. Errors from
    the link are raised as `TransportError`; `open()` may be called again after `close()` to
    reconnect.
    """

    #: False on half-duplex buses where a broadcast REQUEST makes every joint answer at once.
    broadcast_ok: bool = True

    def __init__(self, url: str, read_timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        self.stats = TransportStats()

    @property
    def wire_bytes_per_s(self) -> float | None:
        """Bytes per second each direction can carry, or None when the link is not the limit."""
        return None

    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    @abc.abstractmethod
    def open(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def read(self) -> bytes: ...

    @abc.abstractmethod
    def write(self, data: bytes) -> None: ...

    def write_frames(self, frames: Sequence[bytes]) -> None:
        """Write several frames at once (one syscall or datagram where the link allows)."""
        if frames:
            self.write(b"".join(frames))

    def __enter__(self) -> Transport:
        if not self.is_open:
            self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.url!r})"


def open_transport(
    url: str,
    *,
    baud: int = DEFAULT_BAUD,
    rs485: bool = False,
    read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
    open_now: bool = True,
) -> Transport:
    """Build (and by default open) the transport a `--port` string names.

    Serial options (`baud`, `rs485`) are rejected for UDP and CAN rather than ignored, so a
    mistyped command line fails loudly.
    """
    if not url or not url.strip():
        raise BadUrlError("empty port: give a device path, a pyserial URL or udp://HOST:PORT")
    url = url.strip()
    scheme = urlsplit(url).scheme.lower() if "://" in url else ""
    transport: Transport
    if scheme in ("udp", "can"):
        if rs485:
            raise BadUrlError(f"--rs485 applies to serial ports, not {scheme}:// ({url})")
        if baud != DEFAULT_BAUD:
            raise BadUrlError(f"--baud applies to serial ports, not {scheme}:// ({url})")
        if scheme == "udp":
            from reach_driver.transport_udp import UdpTransport

            transport = UdpTransport.from_url(url, read_timeout_s=read_timeout_s)
        else:
            from reach_driver.transport_can import CanTransport

            transport = CanTransport.from_url(url, read_timeout_s=read_timeout_s)
    else:
        from reach_driver.transport_serial import SerialTransport

        transport = SerialTransport(url, baud=baud, rs485=rs485, read_timeout_s=read_timeout_s)
    if open_now:
        transport.open()
    return transport


def split_host_port(url: str, default_port: int) -> tuple[str, int]:
    """`udp://host:port` -> (host, port), with IPv6 in brackets and a clear error otherwise."""
    parts = urlsplit(url)
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise BadUrlError(f"unexpected path or query in {url!r}: expected udp://HOST[:PORT]")
    try:
        port = parts.port
    except ValueError as exc:
        raise BadUrlError(f"bad port in {url!r}: {exc}") from None
    host = parts.hostname
    if not host:
        raise BadUrlError(f"no host in {url!r}: expected udp://HOST[:PORT]")
    return host, default_port if port is None else port
