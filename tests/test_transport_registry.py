"""The URL-scheme table: built-in transports, plugins through entry points, the template."""

from __future__ import annotations

from importlib.metadata import EntryPoint

import pytest

from reach_driver import BadUrlError, Transport, TransportError, interfaces, open_transport
from reach_driver.transport_serial import SerialTransport
from reach_driver.transport_udp import UdpTransport


class EchoTransport(Transport):
    """A plugin transport: what is written comes back."""

    def __init__(self, url: str, read_timeout_s: float = 0.01) -> None:
        super().__init__(url, read_timeout_s)
        self.buffer: bytes | None = None

    @property
    def is_open(self) -> bool:
        return self.buffer is not None

    def _open_internal(self) -> None:
        self.buffer = b""

    def close(self) -> None:
        self.buffer = None

    def _read_internal(self) -> bytes | None:
        if self.buffer is None:
            raise TransportError(f"{self.url} is not open")
        data, self.buffer = self.buffer, b""
        return data or None

    def _write_internal(self, piece: bytes) -> None:
        if self.buffer is None:
            raise TransportError(f"{self.url} is not open")
        if piece == b"boom":
            raise OSError("cable out")
        self.buffer += piece


@pytest.fixture
def plugins(monkeypatch: pytest.MonkeyPatch) -> None:
    eps = [
        EntryPoint("echo", f"{__name__}:EchoTransport", interfaces.GROUP),
        EntryPoint("udp", f"{__name__}:EchoTransport", interfaces.GROUP),  # cannot hijack
        EntryPoint("notone", "builtins:dict", interfaces.GROUP),
    ]
    monkeypatch.setattr(interfaces, "entry_points", lambda group: eps)


def test_builtin_schemes() -> None:
    assert interfaces.transport_class("udp") is UdpTransport
    assert interfaces.transport_class("") is SerialTransport
    assert interfaces.transport_class("loop") is SerialTransport  # pyserial URLs
    assert interfaces.transport_class("socket") is SerialTransport


def test_plugin_scheme_opens_and_uses_the_template(plugins: None) -> None:
    t = open_transport("echo://anything")
    assert isinstance(t, EchoTransport) and t.is_open and t.stats.opens == 1
    t.write_frames([b"\x01\x00", b"\x02\x00"])
    assert (t.stats.writes, t.stats.bytes_out) == (1, 4)
    assert t.read() == b"\x01\x00\x02\x00" and t.stats.bytes_in == 4
    assert t.read() == b""
    with pytest.raises(TransportError, match="write to echo://anything failed: cable out"):
        t.write(b"boom")
    assert t.stats.write_errors == 1
    t.close()
    with pytest.raises(TransportError, match="not open"):
        t.read()
    assert t.stats.read_errors == 0  # not a link error


def test_plugins_cannot_replace_builtins_or_take_serial_options(plugins: None) -> None:
    assert interfaces.transport_class("udp") is UdpTransport
    assert "echo" in interfaces.transport_schemes()
    with pytest.raises(BadUrlError, match="--baud applies to serial ports"):
        open_transport("echo://x", baud=9600)
    with pytest.raises(BadUrlError, match="not a Transport subclass"):
        open_transport("notone://x")
