"""UDP link to Ethernet arms (and the virtual arm): `udp://HOST[:PORT]`, port 6789 by default.

The socket stays unconnected so datagrams from any other source can be seen, dropped and
counted (a connected socket would drop them silently). The arm answers to our source port,
and streams its heartbeat to whichever host wrote to it last: one commanding client per arm
(a second one takes the stream; `ArmClient` names that when its watchdog trips).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Sequence
from typing import ClassVar

from reach_driver.errors import TransportError
from reach_driver.transport import (
    DEFAULT_READ_TIMEOUT_S,
    DEFAULT_UDP_PORT,
    Transport,
    split_host_port,
)

MAX_DATAGRAM = 1400  # stay under a 1500-byte Ethernet MTU with IP/UDP headers
RECV_BUFFER = 65535  # whole datagrams: a short buffer truncates multi-frame datagrams


class UdpTransport(Transport):
    """Frames travel several to a datagram both ways; each datagram is a whole number of frames."""

    reads_whole_frames: ClassVar[bool] = True
    # No 0x00 on open: a datagram cannot leave a partial frame behind (we split on frame
    # boundaries, and the arm, like reach-sim, ends each datagram's last frame).
    opens_with_delimiter: ClassVar[bool] = False
    # The arm answers each request's sender but streams to the last host that wrote to it:
    # a second client (even a read-only `info`) takes a running client's heartbeat.
    shared_by_other_hosts: ClassVar[bool] = True
    link_errors: ClassVar[tuple[type[BaseException], ...]] = (OSError,)
    read_failed: ClassVar[str] = "receive on"
    write_failed: ClassVar[str] = "send to"

    def __init__(
        self,
        host: str,
        port: int = DEFAULT_UDP_PORT,
        *,
        local_port: int = 0,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        url: str | None = None,
    ) -> None:
        super().__init__(url or f"udp://{host}:{port}", read_timeout_s)
        self.host = host
        self.port = port
        self.local_port = local_port
        self._sock: socket.socket | None = None
        self._peer: tuple[str, int] | None = None

    @classmethod
    def from_url(cls, url: str, read_timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> UdpTransport:
        host, port = split_host_port(url, DEFAULT_UDP_PORT)
        return cls(host, port, read_timeout_s=read_timeout_s, url=url)

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    @property
    def local_address(self) -> tuple[str, int]:
        if self._sock is None:
            raise TransportError(f"{self.url} is not open")
        addr = self._sock.getsockname()
        return addr[0], addr[1]

    def _open_internal(self) -> None:
        try:
            infos = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM)
        except socket.gaierror as exc:
            raise TransportError(f"cannot resolve {self.host!r} for {self.url}: {exc}") from None
        infos.sort(key=lambda info: info[0] != socket.AF_INET)  # "localhost": prefer IPv4
        family, _, _, _, addr = infos[0]
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind(("::" if family == socket.AF_INET6 else "0.0.0.0", self.local_port))
            sock.settimeout(self.read_timeout_s)
        except OSError as exc:
            sock.close()
            raise TransportError(f"cannot bind a UDP socket for {self.url}: {exc}") from None
        self._sock = sock
        self._peer = (str(addr[0]), int(addr[1]))

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _read_internal(self) -> bytes | None:
        sock, peer = self._sock, self._peer
        if sock is None or peer is None:
            raise TransportError(f"{self.url} is not open")
        deadline = time.monotonic() + self.read_timeout_s
        while True:
            try:
                data, source = sock.recvfrom(RECV_BUFFER)
            except (TimeoutError, BlockingIOError):
                return None
            except ConnectionRefusedError:
                return None  # an ICMP port-unreachable from an earlier send; the peer may come back
            if (str(source[0]), int(source[1])) == peer:
                return data
            self.stats.foreign_datagrams += 1
            if time.monotonic() >= deadline:
                return None

    def _pieces(self, frames: Sequence[bytes]) -> Sequence[bytes]:
        """Datagrams of whole frames, each at most MAX_DATAGRAM bytes unless one frame is longer."""
        datagrams: list[bytes] = []
        batch = bytearray()
        for frame in frames:
            if batch and len(batch) + len(frame) > MAX_DATAGRAM:
                datagrams.append(bytes(batch))
                batch.clear()
            batch += frame
        if batch:
            datagrams.append(bytes(batch))
        return datagrams

    def _write_internal(self, piece: bytes) -> None:
        sock, peer = self._sock, self._peer
        if sock is None or peer is None:
            raise TransportError(f"{self.url} is not open")
        sock.sendto(piece, peer)
