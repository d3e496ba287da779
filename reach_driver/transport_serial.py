"""Serial links: a device path or any pyserial URL, RS-232 full duplex or RS-485 half duplex."""

from __future__ import annotations

import errno
import os
import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import ClassVar

import serial

from reach_driver.errors import (
    BadUrlError,
    PortBusyError,
    PortNotFoundError,
    PortPermissionError,
    TransportError,
)
from reach_driver.transport import DEFAULT_BAUD, DEFAULT_READ_TIMEOUT_S, Transport

BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
DEFAULT_RS485_GAP_S = 0.002
RS485_MAX_WAIT_S = 0.05
#: How long after a frame has left the UART its local echo may still be read (generous: an
#: echo let through would read as the arm reporting what we commanded).
RS485_ECHO_WINDOW_S = 0.25
#: Frames written without any echo before the adapter is taken not to echo.
ECHO_MISSES_TO_GIVE_UP = 8
#: errnos meaning another opener holds the port: flock (exclusive=True) or TIOCEXCL.
BUSY_ERRNOS = (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY)


def _available_ports() -> str:
    try:
        from serial.tools import list_ports

        names = sorted(p.device for p in list_ports.comports())
    except Exception:  # listing is a courtesy in an error message, never a new failure
        return ""
    return ", ".join(names) if names else "none"


def _command_of(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            words = f.read().rstrip(b"\0").split(b"\0")
    except OSError:
        return "?"
    command = " ".join(" ".join(w.decode(errors="replace") for w in words).split())
    return command if len(command) <= 120 else command[:117] + "..."


def port_holders(path: str) -> tuple[str, list[int]]:
    """Who holds `path` (Linux, best effort, never raises): ("locked", pids of the flock on it
    in /proc/locks), else ("open", every process with it open in /proc/*/fd), else ("", [])."""
    try:
        real = os.path.realpath(path)
        st = os.stat(real)
    except OSError:
        return "", []
    dev, ino = (os.major(st.st_dev), os.minor(st.st_dev)), st.st_ino
    locked: list[int] = []
    try:
        with open("/proc/locks") as f:
            for line in f:
                # "1: FLOCK  ADVISORY  WRITE 1234 00:19:5 0 EOF" (waiters have "->")
                fields = line.split()
                if len(fields) < 6 or fields[1] != "FLOCK":
                    continue
                major, minor, inode = fields[5].split(":")
                if (int(major, 16), int(minor, 16)) == dev and int(inode) == ino:
                    locked.append(int(fields[4]))
    except (OSError, ValueError):
        locked = []
    if locked:
        return "locked", sorted(set(locked))
    holders = set()
    try:
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return "", []
    for pid in pids:
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:
            continue  # gone, or another user's
        for fd in fds:
            try:
                if os.readlink(f"/proc/{pid}/fd/{fd}") == real:
                    holders.add(pid)
                    break
            except OSError:
                continue
    return ("open", sorted(holders)) if holders else ("", [])


def _describe_holders(path: str) -> str:
    how, pids = port_holders(path)
    if not pids:
        return ""

    def who(pid: int) -> str:
        mine = "this process: " if pid == os.getpid() else ""
        return f"pid {pid} ({mine}{_command_of(pid)})"

    return f" ({how} by {', '.join(who(pid) for pid in pids)})"


class SerialTransport(Transport):
    """8N1 serial; with `rs485=True` frames are written one at a time with idle gaps between.

    On a half-duplex bus the host must not talk over a joint's reply, so each frame waits
    until the line has been quiet for `rs485_gap_s` (after our own bytes have left the UART,
    estimated from the baud rate, and after the last byte received). Broadcast requests are
    refused by the client there, since every joint would answer at once and collide.

    RS-485 also has these two properties (`rs485=True`):

    - **Local echo.** Many two-wire adapters leave the receiver on while transmitting, so
      every byte written comes back, and would read as the arm reporting what we commanded.
      Received frames are compared, from their first byte, with the frames written in the
      last `RS485_ECHO_WINDOW_S`; matching bytes are held back, a whole match is dropped
      (`echo_bytes_dropped`), and the first byte that differs releases what was held,
      unchanged, with the rest of that frame (an adapter that does not echo loses nothing:
      the arm's reply differs from our request by its first bytes at the latest). After
      `ECHO_MISSES_TO_GIVE_UP` frames without an echo and none ever seen, the adapter is
      taken not to echo (`local_echo` False) and nothing is compared any more.
    - **One wire.** Requests, commands and the arm's replies share it, so the budget
      (`wire_bytes_per_s`, which caps heartbeat streaming) is half the line's byte rate:
      the other half is left for what the host sends and the turnaround gaps.

    The port is opened exclusively (on POSIX an advisory flock, which every reach-driver
    takes): a second opener gets `PortBusyError` naming the holder, and the first is left
    undisturbed. Each open starts with a 0x00 (see `Transport.opens_with_delimiter`).
    """

    takes_serial_options: ClassVar[bool] = True
    opens_with_delimiter: ClassVar[bool] = True
    # TypeError/AttributeError: pyserial's fd becomes None under a concurrent close.
    link_errors: ClassVar[tuple[type[BaseException], ...]] = (
        serial.SerialException,
        OSError,
        TypeError,
        AttributeError,
    )

    def __init__(
        self,
        url: str,
        *,
        baud: int = DEFAULT_BAUD,
        rs485: bool = False,
        rs485_gap_s: float = DEFAULT_RS485_GAP_S,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
    ) -> None:
        super().__init__(url, read_timeout_s)
        if baud <= 0:
            raise BadUrlError(f"baud rate must be positive, got {baud}")
        self.baud = baud
        self.rs485 = rs485
        self.rs485_gap_s = rs485_gap_s
        self.broadcast_ok = not rs485
        self._port: serial.SerialBase | None = None
        self._line_busy_until = 0.0  # monotonic time our last byte leaves the UART
        self._last_rx = 0.0
        # RS-485 local echo: bytes written whose echo may still arrive, the received bytes
        # matching them so far, and until when to wait (shared by writer and reader).
        self._echo_lock = threading.Lock()
        self._echo: deque[tuple[bytes, float]] = deque()  # (frame written, echo deadline)
        self._held = bytearray()
        self._foreign = False  # inside a received frame that is not an echo
        self._echo_misses = 0
        #: None until known; True once an echo was seen; False if the adapter does not echo.
        self.local_echo: bool | None = None
        self.echo_bytes_dropped = 0

    @classmethod
    def from_url(
        cls,
        url: str,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        *,
        baud: int = DEFAULT_BAUD,
        rs485: bool = False,
    ) -> SerialTransport:
        return cls(url, baud=baud, rs485=rs485, read_timeout_s=read_timeout_s)

    @property
    def wire_bytes_per_s(self) -> float | None:
        """The line's byte rate at 8N1; on RS-485 half of it (one wire both ways)."""
        rate = self.baud / BITS_PER_BYTE
        return rate / 2.0 if self.rs485 else rate

    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def _open_internal(self) -> None:
        try:
            port = serial.serial_for_url(
                self.url,
                baudrate=self.baud,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=self.read_timeout_s,
                write_timeout=1.0,
                exclusive=True if os.name == "posix" else None,
                do_not_open=True,
            )
            port.open()
        except ValueError as exc:
            raise BadUrlError(f"cannot use {self.url!r} as a serial port: {exc}") from None
        except serial.SerialException as exc:
            raise self._open_error(exc) from None
        try:
            port.reset_input_buffer()
        except (serial.SerialException, OSError):
            pass  # loop:// and some adapters cannot flush; stale bytes are dropped by CRC anyway
        self._port = port

    def _open_error(self, exc: serial.SerialException) -> TransportError:
        code = getattr(exc, "errno", None)
        if code == errno.ENOENT:
            return PortNotFoundError(
                f"no such serial port {self.url}; ports found: {_available_ports()}"
            )
        if code in (errno.EACCES, errno.EPERM):
            return PortPermissionError(
                f"permission denied opening {self.url}: add your user to the group owning it "
                "(usually 'dialout': sudo usermod -aG dialout $USER, then log in again)"
            )
        if code in BUSY_ERRNOS:
            return PortBusyError(
                f"{self.url} is in use{_describe_holders(self.url)}: one program at a time "
                "may drive the arm; close the other (perhaps another reach-driver) and try again"
            )
        return TransportError(f"cannot open serial port {self.url}: {exc}")

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass  # closing a port whose device vanished; nothing left to release

    def _require(self) -> serial.SerialBase:
        port = self._port
        if port is None or not port.is_open:
            raise TransportError(f"serial port {self.url} is not open")
        return port

    def _read_internal(self) -> bytes:
        port = self._require()
        waiting = port.in_waiting
        data: bytes = port.read(waiting or 1)
        if data and not waiting:
            more = port.in_waiting
            if more:
                data += port.read(more)
        if data:
            self._last_rx = time.monotonic()
        if self.rs485:
            return self._strip_echo(data)
        return data

    def _strip_echo(self, data: bytes) -> bytes:
        """`data` less the local echo of what we wrote (see the class docstring)."""
        with self._echo_lock:
            if self.local_echo is False:
                return data
            out = bytearray()
            now = time.monotonic()
            while self._echo and self._echo[0][1] < now:  # its echo never came
                self._echo.popleft()
                self._echo_misses += 1
                if self.local_echo is None and self._echo_misses >= ECHO_MISSES_TO_GIVE_UP:
                    self.local_echo = False  # this adapter does not echo: stop looking
                    self._echo.clear()
            if self._held and not any(p.startswith(self._held) for p, _ in self._echo):
                out += self._held  # what matched an echo that expired: the arm's after all
                self._held.clear()
                self._foreign = True
            for b in data:
                if self._foreign or not self._echo:  # pass a frame that is not an echo whole
                    out.append(b)
                    self._foreign = b != 0
                    continue
                self._held.append(b)
                held = bytes(self._held)
                match = next(
                    (k for k, (piece, _) in enumerate(self._echo) if piece.startswith(held)), None
                )
                if match is None:
                    out += self._held
                    self._held.clear()
                    self._foreign = b != 0
                elif len(held) == len(self._echo[match][0]):  # a whole echoed frame: drop it
                    self.echo_bytes_dropped += len(held)
                    self._held.clear()
                    self.local_echo = True
                    for _ in range(match + 1):  # and any earlier one whose echo was missed
                        self._echo.popleft()
            return bytes(out)

    def _pieces(self, frames: Sequence[bytes]) -> Sequence[bytes]:
        return list(frames) if self.rs485 else [b"".join(frames)]

    def _write_internal(self, piece: bytes) -> None:
        port = self._require()
        if self.rs485:
            self._wait_for_quiet_line()
        now = time.monotonic()
        busy_until = max(now, self._line_busy_until) + len(piece) * BITS_PER_BYTE / self.baud
        if self.rs485 and self.local_echo is not False:
            with self._echo_lock:  # before the write: the echo may be read at once
                self._echo.append((bytes(piece), busy_until + RS485_ECHO_WINDOW_S))
        port.write(piece)
        self._line_busy_until = busy_until

    def _wait_for_quiet_line(self) -> None:
        # Our own bytes must have left; a chattering bus (heartbeats) is waited on only so
        # long, or streaming joints could starve every command.
        give_up = time.monotonic() + RS485_MAX_WAIT_S
        while True:
            now = time.monotonic()
            ready_at = self._line_busy_until + self.rs485_gap_s
            if now < give_up:
                ready_at = max(ready_at, self._last_rx + self.rs485_gap_s)
            if now >= ready_at:
                return
            time.sleep(ready_at - now)
