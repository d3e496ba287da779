"""What crosses the virtual arm's endpoints: input credit, the serial line's timing (and its
half duplex), decoding, handing packets to the firmware, and the output queues written to the
pty and the UDP socket.

`WireIO` is a part of `SimServer` (`reach_sim_bridge.emulator.server`), kept apart because
it is the server's I/O while the server itself paces the physics, runs the loop thread and
answers inspection; the state it uses is the server's, declared below, and all of it runs on
the loop thread.

Nothing a client sends can take that thread from the physics or make memory grow:

- Input budget. Each frame decoded (good or bad) and each reply made costs one unit; every
  sim second earns each endpoint INPUT_UNITS_PER_S units (at most INPUT_BURST banked), so
  the arm's clock keeps real time under any input. Without credit the pty is not read (a
  flood waits in the tty buffer, as its writer's own backlog), and UDP datagrams are read
  but dropped, as is the rest of a datagram once the credit runs out (counted in
  input_dropped_bytes; stale requests would only delay fresh ones). 8000 units/s is about
  seven times what a 115200 baud line carries: a client that fits a real line never notices.
- Output queue with --baud. Frames wait for the emulated line in two queues, replies ahead
  of the stream (heartbeats, status), together at most `out_queue_limit(baud)` bytes
  (OUT_QUEUE_S of wire time). When full, the oldest stream frames make room, then, for a
  reply, the oldest replies (a stream frame finding only replies is dropped). A frame is
  also bounded in time: one older than `out_frame_max_age(baud)` (twice the queue's wire
  time, 0.4 s at 115200) when the line could start it is dropped, as its requester has
  given up; a full-duplex line drains the queue within its wire time, so this bites where
  the line does not drain: a half-duplex wire the host keeps talking on, or a stream frame
  that replies keep overtaking. Drops are whole frames, counted in `stats()`
  (`replies_dropped`, `stream_dropped`). So a reply goes out within OUT_QUEUE_S of wire
  time (unless newer replies push it out under a request flood) and is never older than
  the age limit, nor is the stream. Without --baud the pty's own buffer is the line (when
  full: lost_bytes).

Half duplex (`SimConfig(half_duplex=True)`, `reach-sim --half-duplex`): the pty is one RS-485
wire shared by the host and the arm, timed at `baud`, as the server sees the bytes:

- The arm does not start a frame while host bytes are still arriving: it waits until the
  line has been quiet for TURNAROUND_BYTES byte times after the host's last byte (the
  driver-enable turnaround of an RS-485 transceiver), then sends. Frames already queued go
  back to back, as one talker's.
- A host frame any byte of which arrives while the arm is sending collides: the host's frame
  is lost (never decoded, with whatever of it the arm held: `collisions` frames,
  `collision_bytes`), and so is the arm's frame on the wire (`collided_out`).
- The firmware's half duplex (a broadcast REQUEST that several devices answer gets no
  answer) comes with it. UDP is not a shared wire and is unaffected.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import TYPE_CHECKING

from protocol import DecodeError, Packet, PacketDecoder
from reach_sim_bridge.emulator.events import EventLog
from reach_sim_bridge.emulator.faults import LinkFaults
from reach_sim_bridge.emulator.firmware import Firmware
from reach_sim_bridge.emulator.pty import PtyEndpoint
from reach_sim_bridge.emulator.udp import Address, UdpEndpoint

if TYPE_CHECKING:
    from reach_sim_bridge.emulator.server import SimConfig

BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop
OUT_QUEUE_S = 0.2  # with --baud, frames queued for the line: at most this much wire time
MIN_OUT_QUEUE_BYTES = 512  # ... but room for a broadcast request's answer on a slow line
INPUT_UNITS_PER_S = 8000  # input work per sim second and endpoint: frames + replies
INPUT_BURST = 400  # units banked at most (a burst a client may send at once)
#: Half duplex: byte times of quiet line after the host's last byte before the arm may talk
#: (at 115200 baud 0.35 ms; the driver's RS-485 transport waits 2 ms before it talks).
TURNAROUND_BYTES = 4


def out_queue_limit(baud: int) -> int:
    """Bytes the pty's outgoing queue holds at most at `baud`: OUT_QUEUE_S of wire time."""
    return max(int(OUT_QUEUE_S * baud / BITS_PER_BYTE), MIN_OUT_QUEUE_BYTES)


def out_frame_max_age(baud: int) -> float:
    """Seconds a frame may wait for the line at `baud` before it is dropped: twice the
    queue's wire time (a full queue drains in one)."""
    return 2.0 * out_queue_limit(baud) * BITS_PER_BYTE / baud


class Counters:
    """The server's running counts since the last power cycle (`SimServer.stats()` reads them)."""

    def __init__(self) -> None:
        self.frames_in = 0
        self.frames_out = 0
        self.bytes_in = 0
        self.bytes_out = 0
        self.datagrams_in = 0
        self.datagrams_out = 0
        self.lost_bytes = 0
        self.stream_dropped = 0
        self.replies_dropped = 0
        self.queued_peak_bytes = 0
        self.input_dropped_bytes = 0
        self.collisions = 0
        self.collision_bytes = 0
        self.collided_out = 0
        self.lag_s = 0.0


class WireIO:
    """The endpoints' input and output of `SimServer` (see the module docstring)."""

    config: SimConfig
    firmware: Firmware
    _lock: threading.Lock
    _pty: PtyEndpoint | None
    _udp: UdpEndpoint | None
    _counters: Counters
    _link_faults: LinkFaults
    _link_errors: EventLog
    _pty_decoder: PacketDecoder
    _udp_decoder: PacketDecoder
    _pty_in: deque[tuple[float, bytes | None]]
    _pty_pending: deque[Packet]
    _pty_replies: deque[tuple[float, bytes]]
    _pty_stream: deque[tuple[float, bytes]]
    _pty_queued: int
    _pty_wire: tuple[float, bytes] | None
    _pty_partial: bytes
    _line_rate: float | None
    _out_limit: int | None
    _out_age: float | None
    _rx_free: float
    _tx_free: float
    _turnaround: float
    _rx_garbled: bool
    _udp_out: deque[tuple[float, bytes, Address]]
    _udp_peer: Address | None
    _pty_credit: float
    _udp_credit: float

    # -- input ----------------------------------------------------------------------------
    def _earn(self, sim_s: float) -> None:
        earned = sim_s * INPUT_UNITS_PER_S
        self._pty_credit = min(self._pty_credit + earned, INPUT_BURST)
        self._udp_credit = min(self._udp_credit + earned, INPUT_BURST)

    def _pty_landed(self, now: float) -> bool:
        return bool(self._pty_in) and self._pty_in[0][0] <= now

    def _arrive(self, data: bytes, now: float) -> None:
        """Bytes the host wrote to the pty; with --baud each frame is acted on only when its
        last byte would have crossed the serial line."""
        rate = self._line_rate
        if rate is None:
            self._pty_in.append((now, data))
            return
        landed = max(self._rx_free, now)
        pos = 0
        while pos < len(data):
            end = data.find(0, pos)
            end = len(data) if end < 0 else end + 1
            began, landed = landed, landed + (end - pos) / rate
            piece = data[pos:end]
            if self.config.half_duplex and (began < self._tx_free or self._rx_garbled):
                self._collide(piece, landed)
            else:
                self._pty_in.append((landed, piece))
            pos = end
        self._rx_free = landed

    def _collide(self, piece: bytes, landed: float) -> None:
        """Half duplex: host bytes on the wire while the arm sends (or the rest of a frame
        that did). Both talkers' frames are lost: the host's, from what the arm held of it
        to its delimiter, and the arm's frame on the wire."""
        c = self._counters
        with self._lock:
            c.bytes_in += len(piece)
            c.collision_bytes += len(piece)
            if not self._rx_garbled:
                c.collisions += 1
                self._pty_in.append((landed, None))  # the decoder drops what it holds of it
            if self._pty_wire is not None:
                self._pty_wire = None
                c.collided_out += 1
        self._rx_garbled = not piece.endswith(b"\x00")

    def _read_udp(self, udp: UdpEndpoint, now: float, limit: int) -> None:
        """Up to `limit` datagrams: acted on while there is credit, then dropped (so what
        waits in the socket stays fresh)."""
        for _ in range(limit):
            batch = udp.receive(1)
            if not batch:
                return
            self._receive_datagram(*batch[0], now)

    def _take_input(self, now: float) -> None:
        """Act on the pty's frames, and decode what has landed, while there is credit; what
        is left waits for the credit the next physics steps earn."""
        while self._pty_credit > 0.0:
            if self._pty_pending:
                self._act(self._pty_pending.popleft(), None, now)
            elif self._pty_landed(now):
                self._decode_stream(self._pty_in.popleft()[1])
            else:
                return

    def _on_decode_error(self, error: DecodeError, frame: bytes) -> None:
        # Called from feed(), under the lock, in the loop thread.
        self._link_errors.record(
            f"bad_frame_{error.reason.value}",
            f"{error} ({len(frame)} bytes: {frame[:16].hex(' ')})",
        )
        self.firmware.note_link_error(error)

    def _decode(self, decoder: PacketDecoder, data: bytes) -> tuple[list[Packet], int]:
        """Under the lock: the packets in `data` and the frames (good or bad) it held."""
        stats = decoder.stats
        seen = stats.good_frames + stats.bad_total
        packets = decoder.feed(data)
        return packets, stats.good_frames + stats.bad_total - seen

    def _decode_stream(self, data: bytes | None) -> None:
        if data is None:  # lost in a collision: so is what the decoder held of that frame
            with self._lock:
                self._pty_decoder.reset()
            return
        with self._lock:
            self._counters.bytes_in += len(data)
            packets, frames = self._decode(self._pty_decoder, data)
            self._counters.frames_in += len(packets)
        self._pty_credit -= frames
        self._pty_pending.extend(packets)

    def _receive_datagram(self, data: bytes, sender: Address, now: float) -> None:
        """Act on a datagram's frames in order while there is credit; drop the rest."""
        size = len(data)
        c = self._counters
        with self._lock:
            c.datagrams_in += 1
            c.bytes_in += size
        if not data.endswith(b"\x00"):
            data += b"\x00"  # a datagram ends its last frame
        pos = 0
        while pos < size:
            if self._udp_credit <= 0.0:
                c.input_dropped_bytes += size - pos
                return
            end = data.index(0, pos) + 1
            with self._lock:
                packets, _ = self._decode(self._udp_decoder, data[pos:end])
                c.frames_in += len(packets)
                if packets:  # only a sender of a valid frame gets the stream (see udp.py)
                    self._udp_peer = sender
            self._udp_credit -= 1  # a frame, a bad one, or a stray delimiter
            for packet in packets:
                self._act(packet, sender, now)
            pos = end

    def _act(self, packet: Packet, sender: Address | None, now: float) -> None:
        """Let the firmware act on one packet and queue its replies to where it came from."""
        with self._lock:
            replies = self.firmware.handle(packet)
        if not replies:
            return
        due = now + self.config.faults.latency_ms / 1000.0
        if sender is None:
            self._pty_credit -= len(replies)
            for reply in replies:
                self._queue_pty(reply, due, stream=False)
        else:
            self._udp_credit -= len(replies)
            for reply in replies:
                self._queue_udp(reply, due, sender)

    # -- output ---------------------------------------------------------------------------
    def _send_unprompted(self, packets: list[Packet], now: float) -> None:
        """Heartbeats and status go to the pty and to the UDP peer (the last sender of a
        valid frame)."""
        if not packets:
            return
        due = now + self.config.faults.latency_ms / 1000.0
        for packet in packets:
            if self._pty is not None:
                self._queue_pty(packet, due, stream=True)
            if self._udp is not None and self._udp_peer is not None:
                self._queue_udp(packet, due, self._udp_peer)

    def _queue_pty(self, packet: Packet, ready: float, stream: bool) -> None:
        """Queue a frame for the pty; with --baud within out_queue_limit: the oldest stream
        frames make room, then (for a reply) the oldest replies; a stream frame that finds
        the queue full of replies is dropped."""
        frame = self._link_faults.apply(packet.encode())
        if frame is None:
            return
        size = len(frame)
        limit = self._out_limit
        if limit is not None:
            c = self._counters
            while self._pty_queued + size > limit and self._pty_stream:
                self._pty_queued -= len(self._pty_stream.popleft()[1])
                c.stream_dropped += 1
            if self._pty_queued + size > limit and stream:
                c.stream_dropped += 1  # replies fill the queue: they go first
                return
            while self._pty_queued + size > limit and self._pty_replies:
                self._pty_queued -= len(self._pty_replies.popleft()[1])
                c.replies_dropped += 1  # the oldest: its requester has likely given up
            c.queued_peak_bytes = max(c.queued_peak_bytes, self._pty_queued + size)
        self._pty_queued += size
        (self._pty_stream if stream else self._pty_replies).append((ready, frame))

    def _pty_next(self, now: float) -> tuple[float, bytes] | None:
        """Take the frame the line sends next if one is ready by `now`: (when its last byte
        has crossed the line, frame). The line starts a frame when it is free, the waiting
        reply if one was ready by then, else the oldest stream frame."""
        replies, stream = self._pty_replies, self._pty_stream
        rate = self._line_rate
        while True:
            first = self._pty_first_ready()
            if first is None or first > now:
                return None
            start = first if rate is None else max(self._tx_free, first)
            if self.config.half_duplex:
                start = max(start, now)  # the wire is the host's until now: no sending in the past
            if not self._expire(start):
                break
        queue = replies if replies and replies[0][0] <= start else stream
        _, frame = queue.popleft()
        self._pty_queued -= len(frame)
        if rate is None:
            return start, frame
        self._tx_free = start + len(frame) / rate
        return self._tx_free, frame

    def _expire(self, start: float) -> bool:
        """Drop the frames that would start on the line at `start` older than the age limit
        (counted); whether any was."""
        age = self._out_age
        if age is None:
            return False
        oldest = start - age
        c = self._counters
        dropped = False
        for queue, stream in ((self._pty_replies, False), (self._pty_stream, True)):
            while queue and queue[0][0] < oldest:
                self._pty_queued -= len(queue.popleft()[1])
                dropped = True
                if stream:
                    c.stream_dropped += 1
                else:
                    c.replies_dropped += 1
        return dropped

    def _pty_next_due(self) -> float | None:
        """When the pty output next needs the loop (None: nothing to send)."""
        if self._pty_wire is not None:
            return self._pty_wire[0]
        return self._pty_first_ready()

    def _pty_first_ready(self) -> float | None:
        """When the first queued frame may start: when it is ready, and in half duplex not
        before the host's bytes have landed and the turnaround has passed."""
        heads = [q[0][0] for q in (self._pty_replies, self._pty_stream) if q]
        if not heads:
            return None
        if self.config.half_duplex:
            return max(min(heads), self._rx_free + self._turnaround)
        return min(heads)

    def _clear_pty_out(self) -> None:
        self._pty_replies.clear()
        self._pty_stream.clear()
        self._pty_queued = 0
        self._pty_wire = None
        self._pty_partial = b""

    def _queue_udp(self, packet: Packet, due: float, address: Address) -> None:
        frame = self._link_faults.apply(packet.encode())
        if frame is not None:
            self._udp_out.append((due, frame, address))

    def _flush(self, now: float) -> None:
        pty, udp, c = self._pty, self._udp, self._counters
        if pty is not None:
            while True:
                if self._pty_partial:
                    written = pty.write(self._pty_partial)
                    if written == 0:
                        # Buffer full: nobody is reading. A serial line loses these bytes too.
                        wire = self._pty_wire
                        c.lost_bytes += len(self._pty_partial) + self._pty_queued
                        c.lost_bytes += 0 if wire is None else len(wire[1])
                        self._clear_pty_out()
                        break
                    c.bytes_out += written
                    self._pty_partial = self._pty_partial[written:]
                    continue
                if self._pty_wire is None:
                    self._pty_wire = self._pty_next(now)
                    if self._pty_wire is None:
                        break
                due, frame = self._pty_wire
                if due > now:
                    break
                self._pty_wire = None
                self._pty_partial = frame
                c.frames_out += 1
        if udp is not None:
            while self._udp_out and self._udp_out[0][0] <= now:
                _, frame, address = self._udp_out.popleft()
                c.frames_out += 1
                if udp.send(frame, address):
                    c.bytes_out += len(frame)
                    c.datagrams_out += 1
                else:
                    c.lost_bytes += len(frame)
