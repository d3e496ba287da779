"""REQUESTs and their replies: matched by device *and* packet id, retried, timed out.

A caller writes its requests and waits on a `Waiter`; the reader thread offers every packet
to the waiters wanting its (device, packet id). Nothing else is needed to tell replies
apart, because a device answers one packet per id asked for.

One waiter stays registered across all attempts of a request, so a late reply to the first
REQUEST that arrives just as the retry goes out is still caught (with a waiter per attempt,
it could land between one's removal and the next one's registration, in neither).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Sequence

from protocol import DeviceID, Packet, commands
from protocol.commands import MAX_REQUEST_IDS
from reach_driver.errors import DriverError, RequestTimeoutError
from reach_driver.link import ClientStats
from reach_driver.state import joint_name, packet_names

Key = tuple[int, int]  # (device, packet id)
Replies = dict[int, dict[int, Packet]]  # device -> packet id -> reply


class Waiter:
    """One outstanding request: the (device, packet id) pairs still wanted. Offered packets
    on the reader thread, read by the caller: both under its lock."""

    def __init__(self, wanted: Iterable[Key]) -> None:
        self._lock = threading.Lock()
        self.wanted = set(wanted)
        self.got: dict[Key, Packet] = {}
        self.event = threading.Event()
        self.error: DriverError | None = None

    def still_wants(self, key: Key) -> bool:
        with self._lock:
            return key in self.wanted

    def missing(self) -> set[Key]:
        with self._lock:
            return set(self.wanted)

    def replies(self) -> dict[Key, Packet]:
        with self._lock:
            return dict(self.got)

    def offer(self, packet: Packet) -> None:
        key = (int(packet.device_id), int(packet.packet_id))
        with self._lock:
            if key not in self.wanted:
                return
            self.wanted.discard(key)
            self.got[key] = packet
            done = not self.wanted
        if done:
            self.event.set()

    def fail(self, error: DriverError) -> None:
        self.error = error
        self.event.set()


class Waiters:
    """The outstanding requests by (device, packet id), shared with the reader thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_key: dict[Key, list[Waiter]] = {}

    def add(self, waiter: Waiter) -> None:
        with self._lock:
            for key in waiter.wanted:
                self._by_key.setdefault(key, []).append(waiter)

    def remove(self, waiter: Waiter) -> None:
        with self._lock:
            for key in list(self._by_key):
                items = self._by_key[key]
                if waiter in items:
                    items.remove(waiter)
                if not items:
                    del self._by_key[key]

    def wants(self, key: Key) -> bool:
        """Whether an outstanding request waits for this (device, packet id)."""
        k = (int(key[0]), int(key[1]))
        with self._lock:
            return any(w.still_wants(k) for w in self._by_key.get(k, ()))

    def offer(self, packet: Packet) -> None:
        with self._lock:
            waiters = list(self._by_key.get((int(packet.device_id), int(packet.packet_id)), ()))
        for w in waiters:
            w.offer(packet)

    def fail_all(self, error: Callable[[], DriverError], *, forget: bool = False) -> None:
        """Wake every waiter with `error()` (the link went down or the client closed)."""
        with self._lock:
            waiters = [w for ws in self._by_key.values() for w in ws]
            if forget:
                self._by_key.clear()
        for w in waiters:
            w.fail(error())


class Requester:
    """Writes REQUESTs for one client and collects the replies (see `ArmClient.request_many`)."""

    def __init__(
        self,
        write: Callable[[Sequence[bytes]], object],
        waiters: Waiters,
        stats: ClientStats,
        url: str,
        broadcast_ok: Callable[[], bool],
    ) -> None:
        self._write = write
        self._waiters = waiters
        self._stats = stats
        self._url = url
        self._broadcast_ok = broadcast_ok

    def request_many(
        self,
        devices: Sequence[int],
        ids: Sequence[int],
        *,
        timeout_s: float,
        retries: int,
        partial: bool,
    ) -> Replies:
        devs = [int(d) for d in devices]
        pids = [int(i) for i in ids]
        if not devs or not pids:
            raise ValueError("request needs at least one device and one packet id")
        if DeviceID.BROADCAST in devs:
            raise ValueError(
                "broadcast REQUEST: every joint answers at once (collisions on RS-485) and the "
                "replies cannot be told apart from a timeout; request each device instead"
            )
        if len(devs) > 1 and not self._broadcast_ok():
            # Half duplex: one device at a time, or the replies collide with our requests.
            merged: Replies = {}
            for d in devs:
                merged.update(
                    self._exchange([d], pids, timeout_s=timeout_s, retries=retries, partial=partial)
                )
            return merged
        return self._exchange(devs, pids, timeout_s=timeout_s, retries=retries, partial=partial)

    def _exchange(
        self, devs: list[int], pids: list[int], *, timeout_s: float, retries: int, partial: bool
    ) -> Replies:
        attempts = 1 + retries
        waiter = Waiter((d, p) for d in devs for p in pids)
        self._waiters.add(waiter)  # once, for every attempt: see the module docstring
        try:
            for attempt in range(attempts):
                missing = waiter.missing()
                if not missing:
                    break
                frames = _request_frames(devs, pids, missing)
                self._write(frames)
                self._stats.requests_sent += len(frames)
                if attempt:
                    self._stats.request_retries += len(frames)
                waiter.event.wait(timeout_s)
                if waiter.error is not None:
                    raise waiter.error
        finally:
            self._waiters.remove(waiter)
        got = waiter.replies()
        wanted = waiter.missing()
        if wanted and not partial:
            self._stats.request_timeouts += 1
            never = ", ".join(
                f"{joint_name(d)}: {packet_names(p for dd, p in sorted(wanted) if dd == d)}"
                for d in sorted({d for d, _ in wanted})
            )
            raise RequestTimeoutError(
                f"no reply on {self._url} after {attempts} attempt(s) of "
                f"{timeout_s:.3g} s from {never}"
            )
        out: Replies = {}
        for (d, p), packet in got.items():
            out.setdefault(d, {})[p] = packet
        if not partial:
            for d in devs:
                out.setdefault(d, {})
        return out


def _request_frames(devs: Sequence[int], pids: Sequence[int], wanted: set[Key]) -> list[bytes]:
    """The REQUESTs for what is still wanted, at most MAX_REQUEST_IDS ids each."""
    frames = []
    for d in devs:
        missing = [p for p in pids if (d, p) in wanted]
        for start in range(0, len(missing), MAX_REQUEST_IDS):
            chunk = missing[start : start + MAX_REQUEST_IDS]
            frames.append(commands.request(d, chunk).encode())
    return frames
