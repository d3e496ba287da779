"""Byte-stream bridge between two transports: a software CAN gateway (CAN tunnel <-> the arm's
serial or UDP link), or a serial-to-UDP relay.

Only whole frames are forwarded (up to the last 0x00), so a datagram link on either side
never receives a frame split across datagrams. A side whose reads fail is reopened after a
pause by the thread reading it; the other direction keeps running.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from reach_driver.errors import TransportError
from reach_driver.transport import Transport

log = logging.getLogger(__name__)

MAX_PENDING = 4096  # bytes held without a delimiter before they are dropped as garbage
REOPEN_DELAY_S = 0.5


@dataclass
class BridgeStats:
    bytes_a_to_b: int = 0
    bytes_b_to_a: int = 0
    dropped_bytes: int = 0
    errors: int = 0


class TransportBridge:
    def __init__(self, a: Transport, b: Transport) -> None:
        self.a = a
        self.b = b
        self.stats = BridgeStats()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._locks = {id(a): threading.Lock(), id(b): threading.Lock()}

    def start(self) -> TransportBridge:
        for t in (self.a, self.b):
            if not t.is_open:
                t.open()
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._pump, args=(self.a, self.b, True), daemon=True),
            threading.Thread(target=self._pump, args=(self.b, self.a, False), daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads = []
        self.a.close()
        self.b.close()

    def __enter__(self) -> TransportBridge:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _pump(self, src: Transport, dst: Transport, forward: bool) -> None:
        pending = b""
        while not self._stop.is_set():
            try:
                data = src.read()
            except TransportError as exc:
                self._recover(src, exc)
                pending = b""
                continue
            if not data:
                continue
            pending += data
            cut = pending.rfind(b"\x00")
            if cut < 0:
                if len(pending) > MAX_PENDING:
                    self.stats.dropped_bytes += len(pending)
                    pending = b""
                continue
            frames, pending = pending[: cut + 1], pending[cut + 1 :]
            try:
                with self._locks[id(dst)]:
                    dst.write(frames)
            except TransportError as exc:
                # The pump reading `dst` notices a dead link and reopens it; here the
                # frames are lost (counted) like on a real gateway.
                self.stats.dropped_bytes += len(frames)
                self.stats.errors += 1
                log.debug("bridge: write to %s failed: %s", dst.url, exc)
                continue
            if forward:
                self.stats.bytes_a_to_b += len(frames)
            else:
                self.stats.bytes_b_to_a += len(frames)

    def _recover(self, transport: Transport, exc: TransportError) -> None:
        self.stats.errors += 1
        log.warning("bridge: %s failed (%s); reopening", transport.url, exc)
        with self._locks[id(transport)]:
            transport.close()
            if self._stop.wait(REOPEN_DELAY_S):
                return
            try:
                transport.open()
            except TransportError as again:
                log.warning("bridge: cannot reopen %s: %s", transport.url, again)
