"""Why a client's streamed feedback stopped, when the arm can tell: over a link other hosts
share (UDP) the arm sends its heartbeat to the last host that wrote to it, so another client
can take the stream (or turn it off) while the link itself works.

After a watchdog trip on stale feedback the client asks a streamed device for its heartbeat
rate with the safe mode (`probe_frames`); the answer (`offer`, reader thread) replaces the
trip's reason with what happened to the stream. `problem` asks the same on the caller's
thread, for a control loop whose state stopped arriving. A private link (serial, CAN) has
no other client, so nothing is asked there.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from protocol import Packet, PacketID, commands
from reach_driver.errors import DriverError
from reach_driver.link import EventKind
from reach_driver.safety import SafetyConfig
from reach_driver.state import StateTable, joint_name
from reach_driver.streaming import Stream
from reach_driver.transport import Transport
from reach_driver.watchdog import Watchdog


class StreamDiagnosis:
    """Asks the arm what became of this client's stream (see the module docstring)."""

    def __init__(
        self,
        transport: Transport,
        table: StateTable,
        watchdog: Watchdog,
        *,
        clock: Callable[[], float],
        emit: Callable[[EventKind, str, int | None], None],
        request: Callable[[int, Sequence[int]], dict[int, Packet]],
    ) -> None:
        self._transport = transport
        self._table = table
        self._watchdog = watchdog
        self._clock = clock
        self._emit = emit
        self._request = request
        #: After a trip on stale feedback over a shared link: (device asked for its heartbeat
        #: rate, seconds the feedback had stopped); reader thread only (`offer`).
        self._probe: tuple[int, float] | None = None

    def reset(self) -> None:
        """The link was reopened: an answer to an earlier probe is no longer awaited."""
        self._probe = None

    def probe_frames(
        self,
        stream: Stream | None,
        now: float,
        config: SafetyConfig,
        away_s: float,
        feedback_t: Callable[[int], tuple[float | None, str]],
    ) -> list[bytes]:
        """Over a link other hosts share (UDP), a stream that stopped may have gone to
        another client: ask a streamed device for its heartbeat rate, sent with the safe
        mode; `offer` reads the reply. Nothing to ask otherwise. `away_s`: how long the
        reader thread had been away from the link when it came back."""
        limit = config.watchdog_s
        if stream is None or limit is None or not self._transport.shared_by_other_hosts:
            return []
        # This reader away for most of the limit is the stale feedback's cause (the trip says
        # the machine was busy): the stream kept coming, into the socket. An arm that answers
        # the probe is then no evidence of another client, only that the link works.
        if away_s > limit / 2:
            return []
        # another client takes the whole stream: only when no streamed device's position
        # arrived in the last half watchdog (one quantity of one joint stopping while the
        # others keep arriving is the arm's own fault; a stream that stopped leaves every
        # device within a tick of the stalest one)
        for dev in stream.devices:
            pos = self._table.get(dev).position
            if pos is not None and now - pos.t <= limit / 2:
                return []
        for dev in stream.devices:
            fed, _quantity = feedback_t(dev)
            if fed is not None and now - fed > limit:
                self._probe = (dev, now - fed)
                return [commands.request(dev, [PacketID.HEARTBEAT_FREQUENCY]).encode()]
        return []

    def offer(self, packet: Packet, config: SafetyConfig) -> None:
        """A packet arrived (reader thread). The probe's answer says the link works: the
        stream went elsewhere (or was turned off). Name that as the trip's reason instead of
        a failing link."""
        if self._probe is None or packet.key != (self._probe[0], PacketID.HEARTBEAT_FREQUENCY):
            return
        dev, stopped = self._probe
        self._probe = None
        reason = (
            f"{self._lost(dev, packet)}; this client's feedback had stopped for "
            f"{stopped:.3f} s (watchdog "
            f"{config.watchdog_s:g} s)"
        )
        if self._watchdog.explain(reason):
            self._emit(
                EventKind.WATCHDOG,
                f"{reason}; the armed joints were put in {config.safe_mode.name}",
                dev,
            )

    def problem(self, stream: Stream | None) -> str | None:
        """`ArmClient.stream_problem`: the arm's answer to a rate request, unless the stream
        still reaches this client (then the state came late, and the host was busy)."""
        if stream is None or not self._transport.shared_by_other_hosts:
            return None
        dev = stream.devices[0]
        try:
            reply = self._request(dev, [PacketID.HEARTBEAT_FREQUENCY])
        except DriverError:
            return None
        # The stream still reaching this client (a position within a few ticks of the reply)
        # means the state was late, not taken: the loop's wait ran out while this host did
        # not run it. The arm answering at its rate says nothing of another client then.
        pos = self._table.get(dev).position
        fresh_s = max(3.0 / stream.hz, 0.05)
        if pos is not None and self._clock() - pos.t <= fresh_s:
            return (
                f"the stream still reaches this client ({joint_name(dev)}'s position is "
                f"{1e3 * (self._clock() - pos.t):.0f} ms old): the state came late, not lost; "
                "this host did not run the loop in time (a busy machine)"
            )
        return self._lost(dev, reply[PacketID.HEARTBEAT_FREQUENCY])

    def _lost(self, device: int, rate: Packet) -> str:
        """What an arm that answers us, reporting heartbeat `rate`, says about our stream."""
        hz = rate.data[0] if rate.data else 0
        url = self._transport.url
        if hz:
            return (
                f"another client on this arm's UDP port took the stream: {joint_name(device)} "
                f"still answers {url} and streams at {hz} Hz, but to another host (the arm "
                "sends its heartbeat to the last host that wrote to it; one UDP arm serves one "
                "commanding client: run no info, monitor or second run against it meanwhile)"
            )
        return (
            f"the stream was turned off: {joint_name(device)} still answers {url} but its "
            "heartbeat is 0 Hz (another client on this arm's UDP port stopped it, or the arm "
            "reset)"
        )
