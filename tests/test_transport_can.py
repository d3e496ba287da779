"""The CAN tunnel (docs/can-tunnel.md) on python-can's virtual bus."""

from __future__ import annotations

import itertools
import time

import can
import numpy as np
import pytest
from conftest import wait_until

from protocol import Mode, PacketDecoder, commands
from reach_driver import BadUrlError, open_transport
from reach_driver.transport_can import (
    ARM_TO_HOST_ID,
    FD_LENGTHS,
    HOST_TO_ARM_ID,
    CanTransport,
    CanTunnelConfig,
    TunnelDeframer,
    TunnelFramer,
    parse_can_url,
)

_channels = itertools.count()


def channel() -> str:
    return f"test-tunnel-{next(_channels)}"


def read_for(t, seconds: float = 0.1) -> bytes:
    out = b""
    end = time.monotonic() + seconds
    while True:  # past the deadline, until a read finds nothing: a host pause eats no data
        chunk = t.read()
        out += chunk
        if not chunk and time.monotonic() >= end:
            return out


def test_url_parsing_and_options() -> None:
    interface, ch, cfg, extra = parse_can_url(
        "can://socketcan/can0?tx=0x123&rx=0x124&bitrate=500000"
    )
    assert (interface, ch) == ("socketcan", "can0")
    assert (cfg.tx_id, cfg.rx_id, cfg.fd, cfg.extended) == (0x123, 0x124, False, False)
    assert extra == {"bitrate": 500000}
    _, _, default, _ = parse_can_url("can://virtual/ch0")
    assert (default.tx_id, default.rx_id) == (HOST_TO_ARM_ID, ARM_TO_HOST_ID)
    assert default.swapped() == CanTunnelConfig(ARM_TO_HOST_ID, HOST_TO_ARM_ID)


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("can://virtual", "INTERFACE/CHANNEL"),
        ("can://virtual/ch0?tx=0x800", "11-bit"),
        ("can://virtual/ch0?tx=0x10&rx=0x10", "different"),
        ("can://virtual/ch0?tx=zz", "not an integer"),
        ("can://virtual/ch0?fd=maybe", "use 0 or 1"),
    ],
)
def test_bad_can_urls(url: str, message: str) -> None:
    with pytest.raises(BadUrlError, match=message):
        open_transport(url, open_now=False)


def test_framer_cuts_seven_bytes_per_frame_with_a_wrapping_sequence() -> None:
    framer = TunnelFramer()
    data = bytes(range(1, 200)) * 10  # 1990 bytes -> 285 frames, so the sequence wraps
    payloads = framer.payloads(data)
    assert all(1 < len(p) <= 8 for p in payloads)
    assert [p[0] for p in payloads] == [i & 0xFF for i in range(len(payloads))]
    deframer = TunnelDeframer()
    assert b"".join(deframer.accept(p) for p in payloads) == data
    assert deframer.lost == 0


def test_fd_frames_use_valid_lengths_and_pad_with_delimiters() -> None:
    frames = b"".join(commands.position(d, 1.0).encode() for d in (1, 2, 3, 4, 5, 1, 2))
    payloads = TunnelFramer(fd=True).payloads(frames)
    assert all(len(p) in FD_LENGTHS for p in payloads)
    stream = b"".join(TunnelDeframer().accept(p) for p in payloads)
    assert stream.rstrip(b"\x00") == frames.rstrip(b"\x00")
    assert PacketDecoder().feed(stream) == [
        commands.position(d, 1.0) for d in (1, 2, 3, 4, 5, 1, 2)
    ]


def test_a_lost_can_frame_costs_only_the_bpl_frame_it_carried() -> None:
    packets = [commands.position(5, float(i)) for i in range(6)]
    payloads = TunnelFramer().payloads(b"".join(p.encode() for p in packets))
    del payloads[3]  # somewhere inside the third or fourth BPL frame
    deframer = TunnelDeframer()
    decoder = PacketDecoder()
    got = [p for payload in payloads for p in decoder.feed(deframer.accept(payload))]
    assert deframer.lost == 1
    assert len(got) >= len(packets) - 2
    assert all(p in packets for p in got)  # nothing corrupt is ever handed out
    assert got[-1] == packets[-1]


def test_host_and_gateway_ends_exchange_bytes_on_a_virtual_bus() -> None:
    ch = channel()
    host = open_transport(f"can://virtual/{ch}")
    assert isinstance(host, CanTransport)
    gateway = CanTransport("virtual", ch, host.config.swapped())
    gateway.open()
    sniffer = can.Bus(interface="virtual", channel=ch)
    try:
        request = b"".join(commands.request(d, [3, 2]).encode() for d in (5, 4, 3, 2))
        host.write(request)
        assert read_for(gateway) == request
        ids = set()
        while (msg := sniffer.recv(0.05)) is not None:
            ids.add(msg.arbitration_id)
            assert len(msg.data) <= 8
        assert ids == {HOST_TO_ARM_ID}
        reply = commands.mode(5, Mode.CURRENT).encode() + commands.position(5, 2.5).encode()
        gateway.write(reply)
        assert PacketDecoder().feed(read_for(host)) == [
            commands.mode(5, Mode.CURRENT),
            commands.position(5, 2.5),
        ]
        assert host.stats.lost_can_frames == 0
    finally:
        sniffer.shutdown()
        host.close()
        gateway.close()


def test_the_receiver_counts_a_gap_in_the_sequence() -> None:
    ch = channel()
    host = open_transport(f"can://virtual/{ch}")
    raw = can.Bus(interface="virtual", channel=ch)
    try:
        frame = commands.position(5, 1.0).encode()
        raw.send(
            can.Message(
                arbitration_id=ARM_TO_HOST_ID, data=bytes([0]) + frame[:7], is_extended_id=False
            )
        )
        # seq 1 is lost; seq 2 carries the rest of the frame and then a whole one
        rest = frame[7:] + commands.position(4, 2.0).encode()
        raw.send(
            can.Message(
                arbitration_id=ARM_TO_HOST_ID, data=bytes([2]) + rest[:7], is_extended_id=False
            )
        )
        raw.send(
            can.Message(
                arbitration_id=ARM_TO_HOST_ID, data=bytes([3]) + rest[7:], is_extended_id=False
            )
        )
        raw.send(can.Message(arbitration_id=0x7FF, data=b"\x00junk", is_extended_id=False))
        decoder = PacketDecoder()
        got = decoder.feed(read_for(host))
        assert got == [commands.position(4, 2.0)]
        assert host.stats.lost_can_frames == 1
    finally:
        raw.shutdown()
        host.close()


def test_an_unknown_interface_is_a_clear_transport_error() -> None:
    from reach_driver import TransportError

    with pytest.raises(TransportError, match="cannot open CAN bus can://nosuchbus/x"):
        open_transport("can://nosuchbus/x")


def test_arm_client_reaches_the_virtual_arm_through_a_can_gateway() -> None:
    from protocol import DeviceID, PacketID
    from reach_driver import ArmClient, LimitKind
    from reach_driver.bridge import TransportBridge
    from reach_sim_bridge.emulator.server import SimConfig, SimServer

    ch = channel()
    with SimServer(SimConfig(speed=4.0, pty=False, udp=("127.0.0.1", 0))) as sim:
        assert sim.udp_address is not None
        host, port = sim.udp_address
        gateway = TransportBridge(
            CanTransport("virtual", ch, CanTunnelConfig().swapped()),
            open_transport(f"udp://{host}:{port}", open_now=False),
        )
        with gateway, ArmClient(open_transport(f"can://virtual/{ch}")) as arm:
            assert arm.found_devices == (5, 4, 3, 2, 1)
            assert arm.guard.limit(DeviceID.B, LimitKind.CURRENT).high == 300.0
            q = arm.read_joints().q
            np.testing.assert_allclose(q, sim.snapshot().q, atol=0.01)
            arm.command_position(DeviceID.E, float(q[0]) + 0.2)
            arm.stream((PacketID.POSITION,), 20, [DeviceID.E])
            assert wait_until(lambda: abs(arm.state.q[0] - (q[0] + 0.2)) < 0.02)
        assert arm.transport.stats.lost_can_frames == 0
        assert gateway.stats.bytes_a_to_b > 0 and gateway.stats.bytes_b_to_a > 0
