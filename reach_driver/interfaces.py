"""Which transport a `--port` URL names: a table of URL schemes, like python-can's interfaces.

    open_transport("/dev/ttyUSB0")                # serial, 115200 8N1
    open_transport("/dev/ttyUSB0", rs485=True)   # half duplex: writes spaced, no broadcast
    open_transport("loop://")                     # any pyserial URL
    open_transport("udp://192.168.2.3")           # port 6789 by default
    open_transport("can://virtual/ch0")           # python-can interface/channel, see can-tunnel.md

A device path, or any scheme not in the table (pyserial's `loop://`, `socket://`,
`rfc2217://`...), is a serial port. Other packages add schemes through the
`reach_stack.transports` entry points (`myscheme = "pkg.module:MyTransport"`, a `Transport`
subclass built with `from_url`); the built-in schemes cannot be replaced that way.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from urllib.parse import urlsplit

from reach_driver.errors import BadUrlError
from reach_driver.transport import DEFAULT_BAUD, DEFAULT_READ_TIMEOUT_S, Transport

GROUP = "reach_stack.transports"
SERIAL = "serial"

#: Scheme -> (module, class), imported only when used (each pulls in its link library).
BUILTIN_TRANSPORTS: dict[str, tuple[str, str]] = {
    SERIAL: ("reach_driver.transport_serial", "SerialTransport"),
    "udp": ("reach_driver.transport_udp", "UdpTransport"),
    "can": ("reach_driver.transport_can", "CanTransport"),
}


def transport_schemes() -> dict[str, str]:
    """Every scheme known, built-in and registered, with where its class lives."""
    table = {
        ep.name.lower(): ep.value
        for ep in entry_points(group=GROUP)
        if ep.name.lower() not in BUILTIN_TRANSPORTS
    }
    table.update({name: f"{mod}:{cls}" for name, (mod, cls) in BUILTIN_TRANSPORTS.items()})
    return table


def transport_class(scheme: str) -> type[Transport]:
    """The class for a URL scheme ('' for a device path); pyserial's for unknown schemes."""
    scheme = scheme.lower()
    if scheme in BUILTIN_TRANSPORTS:
        module, name = BUILTIN_TRANSPORTS[scheme]
        cls: object = getattr(importlib.import_module(module), name)
    else:
        found = [ep for ep in entry_points(group=GROUP) if ep.name.lower() == scheme]
        if found:
            try:
                cls = found[0].load()
            except Exception as exc:
                raise BadUrlError(
                    f"transport {scheme}:// is registered as {found[0].value} but failed to "
                    f"load: {type(exc).__name__}: {exc}"
                ) from exc
        else:
            return transport_class(SERIAL)
    if not (isinstance(cls, type) and issubclass(cls, Transport)):
        raise BadUrlError(f"transport {scheme}:// is {cls!r}, not a Transport subclass")
    return cls


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
    cls = transport_class(scheme)
    transport: Transport
    if cls.takes_serial_options:
        serial_options = {"baud": baud, "rs485": rs485}
        transport = cls.from_url(url, read_timeout_s, **serial_options)  # type: ignore[call-arg]
    else:
        if rs485:
            raise BadUrlError(f"--rs485 applies to serial ports, not {scheme}:// ({url})")
        if baud != DEFAULT_BAUD:
            raise BadUrlError(f"--baud applies to serial ports, not {scheme}:// ({url})")
        transport = cls.from_url(url, read_timeout_s)
    if open_now:
        transport.open()
    return transport
