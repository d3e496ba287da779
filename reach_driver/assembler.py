"""One state per heartbeat tick from the joints' streamed POSITION and VELOCITY packets.

The streaming control loop steps once per tick and counts time in ticks (arm time); this
module decides what a tick is when packets are lost or late (see `StateAssembler`).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from protocol import Packet, PacketID, ProtocolError
from protocol.alpha5 import JOINTS, N_JOINTS

N = N_JOINTS

GRACE_FRACTION = 0.25
"""An incomplete tick is handed to the loop this fraction of a period after it began ..."""
GRACE_SPAN_FACTOR = 1.5
"""... or, if later, this many times as long as a whole tick usually takes to arrive (a slow
line, or joints whose heartbeats are not in phase)."""
GAP_FACTOR = 2.5
"""A tick that begins more than this many usual tick spacings after the one before it comes
after a gap: whole ticks were lost (the stream went to another UDP client for a while) or the
host stalled; `Tick.lost` counts the ticks the gap could have held."""


@dataclass(frozen=True)
class Tick:
    """One heartbeat tick's state as the loop takes it."""

    ticks: int  # heartbeat ticks since the stream started
    values: np.ndarray  # position, velocity interleaved per joint
    times: np.ndarray  # arrival times of the values
    serial: int
    currents: np.ndarray  # latest measured currents (NaN until reported)
    partial: bool  # some slot was missing and filled from the previous tick
    seen: np.ndarray  # per slot, the tick its value last arrived in (-1: never)
    lost: int = 0  # ticks that gaps before this one could have held, in all (GAP_FACTOR)


class StateAssembler:
    """Turns the joints' POSITION and VELOCITY heartbeats into one state per heartbeat tick.

    Runs as a reader-thread listener. The joints send their heartbeat packets in a fixed
    order, which is learnt from the first complete tick. A tick begins when a packet arrives
    that comes no later in that order than the last one of the current tick (or when a slot,
    joint x packet, repeats), so ticks are counted even when packets are lost, and a lost
    packet costs only its own tick: neither the count of arm time nor the tick boundary
    drifts (per-slot counts would undercount arm time under steady loss, and completing on
    "every slot refreshed" would leave part of every later state a tick stale after one loss).

    A tick is published once all eight slots are in, or incomplete as soon as the last packet
    in the order has come (the missing ones were lost); when it is the last one that is lost,
    `take` hands the tick out GRACE_FRACTION of a period after it began (the period in wall
    time is the median spacing of recent ticks), or GRACE_SPAN_FACTOR times the usual time a
    whole tick takes to arrive if that is longer. In an incomplete tick a missing position is
    extrapolated from the previous one and its velocity, a missing velocity is held, and each
    slot's `seen` tick lets the loop refuse a value held too long. A tick in which every packet
    is lost is not counted. A packet equal to the one just before it (same slot and value, the
    slot already in) is a duplicate: dropped and counted, never a new tick. The latest CURRENT
    of each joint rides along.

    Ticks lost whole leave no trace in the order, so they are not counted as arm time. When a
    tick begins after a gap (more than GAP_FACTOR usual spacings, in wall time, after the one
    before it), the ticks the gap could have held are added to `Tick.lost`: an upper estimate
    (a host that stalled and then read the stream late makes a gap that lost nothing), for the
    checks that compare two samples across it, never for counting arm time.
    """

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.currents = np.full(N, np.nan)
        self.values = np.full(2 * N, np.nan)
        self.times = np.full(2 * N, np.nan)
        self.have = np.zeros(2 * N, dtype=bool)
        self.prev_values = np.full(2 * N, np.nan)
        self.prev_times = np.full(2 * N, np.nan)
        self.seen = np.full(2 * N, -1, dtype=np.int64)
        self.tick = -1
        self.tick_start = math.nan
        self.published_tick = -1
        self.order: dict[int, int] = {}  # slot -> place in a tick, once learnt
        self.sequence: list[int] = []  # slots of the current tick in arrival order
        self.last_place = -1
        self._starts: deque[float] = deque(maxlen=17)
        self._spans: deque[float] = deque(maxlen=17)  # first to last packet of whole ticks
        self._index = {int(d): i for i, d in enumerate(JOINTS)}
        self._cond = threading.Condition()
        self._latest: Tick | None = None
        self.completed = 0  # states published
        self.skipped = 0  # published but superseded before the loop took them
        self.partial = 0  # published incomplete, after the grace
        self.incomplete = 0  # ticks never published
        self.duplicates = 0  # packets equal to the one just before them, dropped
        self.lost = 0  # ticks gaps in the stream could have held (`Tick.lost`)
        self.gaps = 0  # such gaps
        self._last: tuple[int, float] | None = None  # (slot, value) of the last packet

    def __call__(self, packet: Packet, t: float) -> None:
        pid = packet.packet_id
        if pid != PacketID.POSITION and pid != PacketID.VELOCITY and pid != PacketID.CURRENT:
            return
        i = self._index.get(int(packet.device_id))
        if i is None:
            return
        try:
            value = packet.as_float()
        except ProtocolError:
            return
        with self._cond:
            if pid == PacketID.CURRENT:
                self.currents[i] = value
                return
            slot = 2 * i + (0 if pid == PacketID.POSITION else 1)
            if self._last == (slot, value) and self.have[slot]:
                # The same packet again, right after itself: a link or arm that sends every
                # packet twice. A new tick's value comes after the rest of the tick's slots.
                self.duplicates += 1
                return
            self._last = (slot, value)
            place = self.order.get(slot, -1)
            if self.tick < 0 or self.have[slot] or (0 <= place <= self.last_place):
                self._new_tick(t)
            self.values[slot] = value
            self.times[slot] = t
            self.have[slot] = True
            self.seen[slot] = self.tick
            self.sequence.append(slot)
            self.last_place = max(self.last_place, place)
            if self.published_tick == self.tick:
                return
            if self.have.all():
                if len(self.sequence) == 2 * N:
                    self.order = {s: k for k, s in enumerate(self.sequence)}
                    self._spans.append(t - self.tick_start)
                self._publish()
            elif place == 2 * N - 1:
                self._publish()  # the tick's last packet: the missing ones were lost

    def _new_tick(self, t: float) -> None:
        if self.tick >= 0 and self.published_tick != self.tick:
            self.incomplete += 1
        self.prev_values[self.have] = self.values[self.have]
        self.prev_times[self.have] = self.times[self.have]
        self.have[:] = False
        self.sequence = []
        self.last_place = -1
        if len(self._starts) >= 3 and self.tick >= 0:
            spacing = float(np.median(np.diff(np.asarray(self._starts))))
            gap = t - self.tick_start
            if spacing > 0 and gap > GAP_FACTOR * spacing:
                self.lost += max(1, round(gap / spacing) - 1)
                self.gaps += 1
        self.tick += 1
        self.tick_start = t
        self._starts.append(t)
        # A `take` already waiting must learn this tick's grace end: when its last packet is
        # lost, nothing else would wake it before its timeout.
        self._cond.notify()

    def _publish(self) -> bool:
        """Hand out the current tick (called with the lock held); False if it cannot be
        filled (a slot has never been seen)."""
        values, times = self.values.copy(), self.times.copy()
        missing = ~self.have
        partial = bool(missing.any())
        if partial:
            pos, vel = self.prev_values[0::2], self.prev_values[1::2]
            fill = np.empty(2 * N)
            fill[0::2] = pos + vel * self.period_s
            fill[1::2] = vel
            values[missing] = fill[missing]
            times[missing] = self.prev_times[missing]
            if not np.all(np.isfinite(values)):
                return False
            self.partial += 1
        if self._latest is not None:
            self.skipped += 1
        self.completed += 1
        self.published_tick = self.tick
        self._latest = Tick(
            self.tick,
            values,
            times,
            self.completed,
            self.currents.copy(),
            partial,
            self.seen.copy(),
            self.lost,
        )
        self._cond.notify()
        return True

    def _grace_end(self) -> float | None:
        """When the open tick may be handed out incomplete (None: not yet knowable)."""
        if self.tick < 0 or self.published_tick == self.tick or len(self._starts) < 3:
            return None
        spacing = float(np.median(np.diff(np.asarray(self._starts))))
        if not spacing > 0:
            return None
        span = float(np.median(np.asarray(self._spans))) if self._spans else 0.0
        return self.tick_start + max(GRACE_FRACTION * spacing, GRACE_SPAN_FACTOR * span)

    def take(self, timeout: float) -> Tick | None:
        """The newest state not yet taken; None if nothing came within `timeout` s."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._latest is None:
                now = time.monotonic()
                grace = self._grace_end()
                if grace is not None and now >= grace and self._publish():
                    break
                if now >= deadline:
                    break
                until = deadline if grace is None or grace <= now else min(deadline, grace)
                self._cond.wait(max(until - now, 1e-4))
            latest, self._latest = self._latest, None
            return latest

    def newer_than(self, serial: int) -> bool:
        return self.completed > serial
