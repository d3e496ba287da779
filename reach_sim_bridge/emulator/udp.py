"""The arm's Ethernet face: a UDP socket answering each datagram's sender.

Source policy. Replies go to the sender of the datagram holding the request. The stream
(heartbeats, status reports) goes to one peer: the sender of the latest datagram holding at
least one valid frame the arm read (good COBS and CRC; the packet need not be one it acts
on; a datagram dropped for want of input credit, see server.py, does not count); a
valid frame from another address makes that address the peer. A datagram with no valid
frame (garbage, bad CRC, empty) changes nothing: it is counted (datagrams and bytes in, bad
frames or discarded bytes, and the link-error flag on the base, as on the serial line),
dropped, and never answered. So a stray datagram cannot take the stream from a driver,
while a driver restarted on a new port takes it back with its first frame.
"""

from __future__ import annotations

import contextlib
import ipaddress
import socket

DEFAULT_UDP_HOST = "127.0.0.1"
DEFAULT_UDP_PORT = 6789
MAX_DATAGRAM = 65535  # never truncate a datagram carrying many frames

Address = tuple[str, int]


def parse_udp_address(text: str) -> Address:
    """'HOST:PORT', ':PORT', 'PORT' or '[V6]:PORT' -> (host, port); loopback unless given."""
    text = text.strip()
    host, port_text = DEFAULT_UDP_HOST, text
    if text.startswith("["):
        end = text.find("]")
        if end < 0 or not text[end + 1 :].startswith(":"):
            raise ValueError(f"expected [IPV6]:PORT, got {text!r}")
        host, port_text = text[1:end], text[end + 2 :]
    elif ":" in text:
        host, _, port_text = text.rpartition(":")
        host = host or DEFAULT_UDP_HOST
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"UDP port must be a number, got {port_text!r} in {text!r}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"UDP port must be in 0..65535, got {port}")
    return host, port


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class UdpEndpoint:
    """Non-blocking UDP socket; port 0 picks a free port (see `address`)."""

    def __init__(self, host: str, port: int) -> None:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self._sock.bind((host, port))
        except OSError as exc:
            self._sock.close()
            raise OSError(exc.errno, f"cannot serve UDP on {host}:{port}: {exc.strerror}") from exc
        self._sock.setblocking(False)
        bound = self._sock.getsockname()
        self.address: Address = (str(bound[0]), int(bound[1]))

    def fileno(self) -> int:
        return self._sock.fileno()

    def receive(self, limit: int = 64) -> list[tuple[bytes, Address]]:
        """Datagrams waiting now (at most `limit`, so one sender cannot starve the loop)."""
        out: list[tuple[bytes, Address]] = []
        for _ in range(limit):
            try:
                data, sender = self._sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:  # ICMP port unreachable from an earlier reply
                continue
            out.append((data, (str(sender[0]), int(sender[1]))))
        return out

    def send(self, data: bytes, address: Address) -> bool:
        """Send one datagram; False when the kernel refused it (the datagram is lost)."""
        try:
            self._sock.sendto(data, address)
        except (BlockingIOError, ConnectionRefusedError, OSError):
            return False
        return True

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()
