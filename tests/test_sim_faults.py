"""Fault injection, address parsing and rate-limited event logging of the virtual arm."""

from __future__ import annotations

import logging

import pytest

from protocol import DeviceID, Packet, PacketDecoder, PacketID, commands
from reach_sim_bridge.emulator.events import EventLog
from reach_sim_bridge.emulator.faults import (
    FaultConfig,
    LinkFaults,
    StuckReading,
    parse_torque_scale,
    torque_scales,
)
from reach_sim_bridge.emulator.firmware import Firmware
from reach_sim_bridge.emulator.server import SimConfig, SimServer
from reach_sim_bridge.emulator.udp import is_loopback, parse_udp_address
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.params import ArmParams

FRAME = commands.position(5, 1.25).encode()


def test_corrupt_rate_one_changes_every_byte_and_the_decoder_rejects_the_frame() -> None:
    faults = LinkFaults(FaultConfig(corrupt_rate=1.0), seed=0)
    damaged = faults.apply(FRAME)
    assert damaged is not None and len(damaged) == len(FRAME)
    assert all(a != b for a, b in zip(damaged, FRAME, strict=True))
    assert faults.corrupted_bytes == len(FRAME)
    decoder = PacketDecoder()
    assert decoder.feed(damaged + b"\x00") == []


def test_drop_and_corrupt_rates_are_statistical_and_seeded() -> None:
    config = FaultConfig(drop_rate=0.3, corrupt_rate=0.05)
    runs = []
    for _ in range(2):
        faults = LinkFaults(config, seed=42)
        runs.append([faults.apply(FRAME) for _ in range(2000)])
        assert 0.25 < faults.dropped_frames / 2000 < 0.35
        sent_bytes = sum(len(f) for f in runs[-1] if f is not None)
        assert 0.03 < faults.corrupted_bytes / sent_bytes < 0.07
    assert runs[0] == runs[1]
    healthy = LinkFaults(FaultConfig(), seed=1)
    assert all(healthy.apply(FRAME) == FRAME for _ in range(100))


def test_fault_config_and_torque_scale_parsing_refuse_bad_values() -> None:
    assert parse_torque_scale("c=0.5") == (2, 0.5)
    assert torque_scales(["E=0.25", "B=0.1", "E=0.5"]) == (0.5, 1.0, 1.0, 0.1)
    for text, message in (
        ("X=0.5", "JOINT one of"),
        ("E0.5", "JOINT=SCALE"),
        ("E=abc", "not a number"),
        ("D=-1", r"\[0, 1\]"),
    ):
        with pytest.raises(ValueError, match=message):
            parse_torque_scale(text)
    with pytest.raises(ValueError, match="probability"):
        FaultConfig(drop_rate=2.0)
    with pytest.raises(ValueError, match="latency_ms"):
        FaultConfig(latency_ms=-1.0)
    with pytest.raises(ValueError, match="torque scale of joint C"):
        FaultConfig(torque_scale=(1.0, 1.0, 1.5, 1.0))


def test_randomized_parameters_are_reproducible_and_torque_scale_applied() -> None:
    faults = FaultConfig(randomize_seed=7, torque_scale=(0.25, 1.0, 1.0, 1.0))
    config = SimConfig(pty=False, udp=("127.0.0.1", 0), faults=faults)
    first, second = SimServer(config).arm.params, SimServer(config).arm.params
    nominal = ArmParams()
    assert first.damping == second.damping and first.armature == second.armature
    assert first.damping != nominal.damping and first.link_mass_kg != nominal.link_mass_kg
    assert first.torque_scale == (0.25, 1.0, 1.0, 1.0)
    other = SimServer(
        SimConfig(pty=False, udp=("127.0.0.1", 0), faults=FaultConfig(randomize_seed=8))
    ).arm.params
    assert other.damping != first.damping


@pytest.mark.parametrize(
    ("text", "address"),
    [
        ("127.0.0.1:6789", ("127.0.0.1", 6789)),
        (":7000", ("127.0.0.1", 7000)),
        ("7001", ("127.0.0.1", 7001)),
        ("[::1]:7002", ("::1", 7002)),
        ("192.168.2.3:6789", ("192.168.2.3", 6789)),
    ],
)
def test_udp_addresses_default_to_loopback(text: str, address: tuple[str, int]) -> None:
    assert parse_udp_address(text) == address


def test_bad_udp_addresses_and_loopback_detection() -> None:
    for text in ("host:", "1.2.3.4:70000", "[::1]6789"):
        with pytest.raises(ValueError):
            parse_udp_address(text)
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.2.3")


def test_event_log_counts_everything_and_logs_each_reason_once_per_interval(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = [100.0]
    events = EventLog(logging.getLogger("test.events"), interval=1.0, clock=lambda: clock[0])
    with caplog.at_level(logging.WARNING, logger="test.events"):
        for _ in range(50):
            events.record("crc", "bad CRC")
        events.record("cobs", "bad COBS")
        clock[0] += 1.5
        events.record("crc", "bad CRC again")
    assert events.snapshot() == {"crc": 51, "cobs": 1}
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 3
    assert messages[0].startswith("crc: bad CRC [1 so far]")
    assert messages[2] == "crc: bad CRC again [51 so far] (+49 more like it since the last report)"


def test_firmware_errors_are_logged(caplog: pytest.LogCaptureFixture) -> None:
    fw = Firmware(Alpha5Arm())
    with caplog.at_level(logging.WARNING, logger="reach_sim_bridge.emulator.firmware"):
        fw.handle(Packet(5, PacketID.MODE, b""))
    assert any(
        "bad_payload" in r.getMessage() and "empty MODE" in r.getMessage() for r in caplog.records
    )


def test_a_stuck_reading_keeps_its_value_from_its_arm_time_on() -> None:
    """`StuckReading`: from its arm time on, E's VELOCITY (answers and heartbeats alike)
    carries the value it had then, while the joint moves on and its POSITION follows."""
    E = DeviceID.E
    fw = Firmware(Alpha5Arm())
    fw.handle(commands.heartbeat_set(E, [PacketID.VELOCITY]))
    fw.handle(commands.heartbeat_frequency(E, 50))
    fw.handle(commands.velocity(E, 0.3))
    fw.inject_stuck(StuckReading(E, PacketID.VELOCITY, from_s=0.5))
    fw.tick(0.5)

    def velocity() -> float:
        return fw.handle(commands.request(E, [PacketID.VELOCITY]))[0].as_float()

    stuck = velocity()
    assert stuck == pytest.approx(0.3, abs=0.05)
    fw.handle(commands.velocity(E, -0.3))
    q0 = float(fw.arm.q[0])
    beats = [p.as_float() for p in fw.tick(1.0) if p.key == (E, PacketID.VELOCITY)]
    assert len(beats) == 50 and set(beats) == {stuck}
    assert velocity() == stuck
    assert float(fw.arm.qdot[0]) == pytest.approx(-0.3, abs=0.02)  # the joint moved on
    assert float(fw.arm.q[0]) < q0 - 0.2
    fw.unstick(E, PacketID.VELOCITY)
    assert velocity() == pytest.approx(-0.3, abs=0.02)
