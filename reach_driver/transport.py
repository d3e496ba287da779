"""The one byte-stream interface every link to the arm implements (python-can's `BusABC`).

The rest of the driver never knows whether bytes travel over a tty, UDP datagrams or a CAN
tunnel; `reach_driver.interfaces.open_transport` picks the class from a URL.

`read()`, `write()` and `write_frames()` are templates: they keep the statistics and turn
the link library's exceptions into `TransportError` once, here, and call each transport's
small `_read_internal()` / `_write_internal()` (like `BusABC.recv` and `_recv_internal`).
"""

from __future__ import annotations

import abc
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar
from urllib.parse import urlsplit

from protocol.alpha5 import SERIAL_BAUD
from reach_driver.errors import BadUrlError, TransportError

DEFAULT_BAUD = SERIAL_BAUD
DEFAULT_UDP_PORT = 6789
DEFAULT_READ_TIMEOUT_S = 0.01
DELIMITER = b"\x00"


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

    A subclass implements `is_open`, `_open_internal`, `close`, `_read_internal` and
    `_write_internal`, and names in `link_errors` the exceptions its library raises.
    """

    #: False on half-duplex buses where a broadcast REQUEST makes every joint answer at once.
    broadcast_ok: bool = True
    #: Whether `from_url` takes the serial options (`baud`, `rs485`); elsewhere they are
    #: refused rather than ignored, so a mistyped command line fails loudly.
    takes_serial_options: ClassVar[bool] = False
    #: Each read returns whole frames (datagrams): the template ends it with a 0x00 so a
    #: truncated tail can never merge with the next read's first frame.
    reads_whole_frames: ClassVar[bool] = False
    #: A byte stream (serial, the CAN tunnel): `open()` writes one 0x00 first, so the arm's
    #: decoder drops any partial frame a previous host left on the line instead of gluing
    #: our first request to it. Not for datagrams: the arm ends each datagram's last frame.
    opens_with_delimiter: ClassVar[bool] = False
    #: The arm sends its heartbeat to whoever wrote to it last (UDP: the last source address),
    #: so any other client's packet takes the stream; serial and the tunnel are one host's.
    shared_by_other_hosts: ClassVar[bool] = False
    #: The link library's exceptions, reported as `TransportError` by the templates.
    link_errors: ClassVar[tuple[type[BaseException], ...]] = (OSError,)
    #: How the templates' messages name a failed read and write ("read from URL failed: ...").
    read_failed: ClassVar[str] = "read from"
    write_failed: ClassVar[str] = "write to"

    def __init__(self, url: str, read_timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        self.stats = TransportStats()
        self._write_lock = threading.Lock()

    @classmethod
    def from_url(cls, url: str, read_timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> Transport:
        """Build (not open) the transport a URL names; plugins may keep this default."""
        return cls(url, read_timeout_s)

    @property
    def wire_bytes_per_s(self) -> float | None:
        """Bytes per second each direction can carry, or None when the link is not the limit."""
        return None

    # -- the templates -----------------------------------------------------------------------

    def open(self) -> None:
        if self.is_open:
            return
        self._open_internal()
        self.stats.opens += 1
        if self.opens_with_delimiter:
            try:
                self._write_pieces([DELIMITER])
            except TransportError:
                self.close()  # never left open half set up
                raise

    def read(self) -> bytes:
        """What arrived within `read_timeout_s` (b"" if nothing)."""
        try:
            data = self._read_internal()
        except self.link_errors as exc:
            self.stats.read_errors += 1
            raise TransportError(f"{self.read_failed} {self.url} failed: {exc}") from None
        if data is None:
            return b""
        self.stats.bytes_in += len(data)
        if self.reads_whole_frames and not data.endswith(b"\x00"):
            data += b"\x00"  # an extra 0x00 is only an empty piece to the decoder
        return data

    def write(self, data: bytes) -> None:
        """Write bytes as one piece."""
        self._write_pieces([data])

    def write_frames(self, frames: Sequence[bytes]) -> None:
        """Write several frames at once (one syscall or datagram where the link allows)."""
        if frames:
            self._write_pieces(self._pieces(frames))

    def _write_pieces(self, pieces: Sequence[bytes]) -> None:
        with self._write_lock:
            for piece in pieces:
                try:
                    self._write_internal(piece)
                except self.link_errors as exc:
                    self.stats.write_errors += 1
                    raise TransportError(f"{self.write_failed} {self.url} failed: {exc}") from None
                self.stats.bytes_out += len(piece)
                self.stats.writes += 1

    # -- what each transport implements --------------------------------------------------------

    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    @abc.abstractmethod
    def _open_internal(self) -> None:
        """Open the link (only called while closed); raise `TransportError` if it cannot be."""

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def _read_internal(self) -> bytes | None:
        """Bytes received within `read_timeout_s`, or None when nothing came; raise
        `TransportError` when not open, or one of `link_errors`."""

    @abc.abstractmethod
    def _write_internal(self, piece: bytes) -> None:
        """Send one piece; raise `TransportError` when not open, or one of `link_errors`."""

    def _pieces(self, frames: Sequence[bytes]) -> Sequence[bytes]:
        """How `write_frames` cuts frames into writes: all at once unless the link says."""
        return [b"".join(frames)]

    def __enter__(self) -> Transport:
        if not self.is_open:
            self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.url!r})"


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
