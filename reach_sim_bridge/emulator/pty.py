"""A pseudo-terminal that looks like the arm's serial port to any client (pyserial, minicom).

The slave side is put in raw mode (no echo, no line discipline, 8 bits) so binary frames
pass untouched, and kept open by us so the settings and the device survive clients that
come and go. The master side is non-blocking: the server's loop never waits on a client.
"""

from __future__ import annotations

import contextlib
import errno
import os
import termios
import tty
from pathlib import Path


class PtyEndpoint:
    """The arm's end of a pty; clients open `path` (or the stable `link` to it)."""

    def __init__(self, link: str | os.PathLike[str] | None = None) -> None:
        self._master, self._slave = os.openpty()
        try:
            tty.setraw(self._slave, termios.TCSANOW)
            attrs = termios.tcgetattr(self._slave)
            attrs[3] &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG)
            termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
            os.set_blocking(self._master, False)
            self.path = os.ttyname(self._slave)
            self.link: Path | None = None
            if link is not None:
                self.link = Path(link)
                _point_link(self.link, self.path)
        except BaseException:
            os.close(self._master)
            os.close(self._slave)
            raise
        self._closed = False

    def fileno(self) -> int:
        return self._master

    def read(self, limit: int = 4096) -> bytes:
        """What the client wrote, or b'' when nothing is waiting."""
        try:
            return os.read(self._master, limit)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: no client has the slave open on some kernels
            if exc.errno == errno.EIO:
                return b""
            raise

    def write(self, data: bytes) -> int:
        """Bytes accepted by the pty (0 when its buffer is full: nobody is reading)."""
        try:
            return os.write(self._master, data)
        except BlockingIOError:
            return 0
        except OSError as exc:
            if exc.errno == errno.EIO:
                return 0
            raise

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.link is not None:
            _remove_link(self.link, self.path)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def _point_link(link: Path, target: str) -> None:
    """Make `link` a symlink to `target`, replacing a stale symlink but never a real file."""
    if link.is_symlink():
        pass  # a leftover from an earlier run (or a restart): replace it below
    elif link.exists():
        raise FileExistsError(f"--link {link} exists and is not a symlink; refusing to replace it")
    if not link.parent.is_dir():
        raise FileNotFoundError(f"--link {link}: directory {link.parent} does not exist")
    tmp = link.with_name(f".{link.name}.{os.getpid()}.tmp")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    os.symlink(target, tmp)
    os.replace(tmp, link)  # atomic: a client never sees the link missing


def _remove_link(link: Path, target: str) -> None:
    """Remove the link only if it still points at our pty (a newer server may own it)."""
    with contextlib.suppress(OSError):
        if link.is_symlink() and os.readlink(link) == target:
            link.unlink()
