"""The emulated joint firmware driving the real MuJoCo arm, without any I/O.

Packets go in through Firmware.handle(), sim time advances through tick() as fast as the CPU
allows, and every assertion is about what the arm would put on the wire or where the joints
went.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol import (
    CrcError,
    DeviceID,
    HardwareStatus,
    Mode,
    Packet,
    PacketID,
    commands,
)
from protocol.payload import pack_floats
from reach_sim_bridge.emulator.firmware import ALPHA5_DEVICES, Firmware, FirmwareConfig
from reach_sim_bridge.model.arm import Alpha5Arm
from reach_sim_bridge.model.sensors import SensorNoise

A, B, C, D, E = DeviceID.A, DeviceID.B, DeviceID.C, DeviceID.D, DeviceID.E
BROADCAST = DeviceID.BROADCAST
INDEX: dict[int, int] = {E: 0, D: 1, C: 2, B: 3}  # E D C B order of the arm's arrays
RATE: dict[int, float] = {E: 0.5236, D: 0.5236, C: 0.5236, B: 0.8727}


@pytest.fixture
def fw() -> Firmware:
    return Firmware(Alpha5Arm())


def ask(fw: Firmware, device: int, *ids: int) -> list[Packet]:
    return fw.handle(commands.request(device, list(ids)))


def one(fw: Firmware, device: int, pid: int) -> Packet:
    replies = ask(fw, device, pid)
    assert len(replies) == 1, replies
    assert replies[0].key == (device, pid)
    return replies[0]


def value(fw: Firmware, device: int, pid: int) -> float:
    return one(fw, device, pid).as_float()


def run_until(fw: Firmware, done, limit_s: float, step_s: float = 0.05) -> float:  # noqa: ANN001
    """Tick until done() holds; the sim time it took (fails past limit_s of sim time)."""
    start = fw.time
    while not done():
        assert fw.time - start < limit_s, f"not done after {limit_s} s of sim time"
        fw.tick(step_s)
    return fw.time - start


# -- identity, limits, requests ------------------------------------------------------------
def test_identity_of_every_device(fw: Firmware) -> None:
    for spec in ALPHA5_DEVICES:
        dev = spec.device_id
        replies = ask(
            fw,
            dev,
            PacketID.SOFTWARE_VERSION,
            PacketID.SERIAL_NUMBER,
            PacketID.MODEL_NUMBER,
            PacketID.DEVICE_ID,
            PacketID.MODE,
        )
        assert [r.packet_id for r in replies] == [
            PacketID.SOFTWARE_VERSION,
            PacketID.SERIAL_NUMBER,
            PacketID.MODEL_NUMBER,
            PacketID.DEVICE_ID,
            PacketID.MODE,
        ]
        assert all(r.device_id == dev for r in replies)
        assert replies[0].u8s() == list(FirmwareConfig().software_version)
        assert replies[1].as_float() == spec.serial_number
        assert replies[2].as_float() == FirmwareConfig().model_number
        assert replies[3].u8s() == [int(dev)]
        assert replies[4].u8s() == [Mode.STANDBY]


def test_default_limits_in_max_min_order(fw: Firmware) -> None:
    arm = fw.arm
    for dev, i in INDEX.items():
        hi, lo = one(fw, dev, PacketID.POSITION_LIMITS).floats()
        assert (lo, hi) == pytest.approx(tuple(arm.position_limits[i]), abs=1e-6)
        assert one(fw, dev, PacketID.VELOCITY_LIMITS).floats() == pytest.approx(
            [RATE[dev], -RATE[dev]], abs=1e-6
        )
    for dev, limit in ((E, 600.0), (D, 600.0), (C, 600.0), (B, 300.0)):
        assert one(fw, dev, PacketID.CURRENT_LIMITS).floats() == [limit, -limit]
    assert one(fw, A, PacketID.POSITION_LIMITS).floats() == pytest.approx([13.3, 1.3], abs=1e-5)
    assert one(fw, A, PacketID.VELOCITY_LIMITS).floats() == [3.0, -3.0]


def test_positions_are_the_arms_angles(fw: Firmware) -> None:
    replies = ask(fw, BROADCAST, PacketID.POSITION)
    assert [r.device_id for r in replies] == [A, B, C, D, E]
    q = fw.arm.q
    for r in replies[1:]:
        assert r.as_float() == pytest.approx(q[INDEX[r.device_id]], abs=1e-6)
    assert replies[0].as_float() == pytest.approx(fw.arm.jaw_mm, abs=1e-5)


def test_request_answers_each_id_in_order_and_broadcast_by_every_joint(fw: Firmware) -> None:
    ids = [PacketID.VELOCITY, PacketID.POSITION, PacketID.CURRENT, PacketID.MODE]
    assert [r.packet_id for r in ask(fw, D, *ids)] == ids
    replies = ask(fw, BROADCAST, PacketID.POSITION, PacketID.VELOCITY)
    assert [r.key for r in replies] == [
        (d, p) for d in (A, B, C, D, E) for p in (PacketID.POSITION, PacketID.VELOCITY)
    ]


def test_limits_are_settable_and_checked(fw: Firmware) -> None:
    fw.handle(commands.limits(D, PacketID.POSITION_LIMITS, 2.5, 0.5))
    assert one(fw, D, PacketID.POSITION_LIMITS).floats() == [2.5, 0.5]
    fw.handle(commands.limits(C, PacketID.CURRENT_LIMITS, 200.0, -100.0))
    assert one(fw, C, PacketID.CURRENT_LIMITS).floats() == [200.0, -100.0]
    assert fw.arm.current_limits_mA[INDEX[C]] == 200.0  # the drive follows
    # [min, max] (the old order) is refused and changes nothing.
    fw.handle(Packet(D, PacketID.POSITION_LIMITS, pack_floats(0.5, 2.5)))
    assert one(fw, D, PacketID.POSITION_LIMITS).floats() == [2.5, 0.5]
    fw.handle(Packet(E, PacketID.VELOCITY_LIMITS, pack_floats(0.3, 0.1)))  # excludes 0
    fw.handle(Packet(E, PacketID.VELOCITY_LIMITS, pack_floats(1.0)))  # one float only
    assert fw.errors.counts == {"bad_limits": 2, "bad_payload": 1}
    assert one(fw, E, PacketID.VELOCITY_LIMITS).floats() == pytest.approx([0.5236, -0.5236])


def test_end_effector_pose_from_the_base_device(fw: Firmware) -> None:
    pose = one(fw, E, PacketID.KM_END_POS).floats()
    assert pose == pytest.approx(fw.arm.end_effector_pose(), abs=1e-3)
    assert ask(fw, D, PacketID.KM_END_POS) == []  # only the base does kinematics
    assert [r.device_id for r in ask(fw, BROADCAST, PacketID.KM_END_POS)] == [E]


# -- control ---------------------------------------------------------------------------------
def test_position_mode_reaches_targets_within_a_hundredth_of_a_radian(fw: Firmware) -> None:
    q0 = fw.arm.q
    targets = {E: q0[0] + 0.6, D: q0[1] + 0.5, C: q0[2] - 0.5, B: q0[3] - 0.8}
    for dev, target in targets.items():
        fw.handle(commands.position(dev, target))
    fw.handle(commands.position(A, 10.0))
    assert one(fw, D, PacketID.MODE).u8s() == [Mode.POSITION]  # implicit switch

    def reached() -> bool:
        q = fw.arm.q
        return all(abs(q[INDEX[d]] - t) < 0.01 for d, t in targets.items())

    took = run_until(fw, reached, limit_s=4.0)
    # Rate-limited: the largest move (B, 0.8 rad at 0.8727 rad/s) cannot be faster.
    assert took >= 0.8 / 0.8727
    fw.tick(1.0)  # and it stays there (D and C against gravity)
    for dev, target in targets.items():
        assert value(fw, dev, PacketID.POSITION) == pytest.approx(target, abs=0.01)
        assert abs(value(fw, dev, PacketID.VELOCITY)) < 0.01
    assert value(fw, A, PacketID.POSITION) == pytest.approx(10.0, abs=0.05)


def test_out_of_limit_position_commands_are_ignored(fw: Firmware) -> None:
    q0 = fw.arm.q
    fw.handle(commands.position(D, 3.6))  # above D's 3.4034
    fw.tick(0.5)
    assert one(fw, D, PacketID.MODE).u8s() == [Mode.STANDBY]
    assert value(fw, D, PacketID.POSITION) == pytest.approx(q0[1], abs=0.002)
    assert fw.ignored.counts["position_out_of_limits"] == 1
    assert fw.errors.counts == {}


def test_velocity_mode_moves_at_the_commanded_rate_and_saturates(fw: Firmware) -> None:
    fw.handle(commands.velocity(E, 0.3))
    fw.handle(commands.velocity(C, -2.0))  # saturates at the firmware rate limit
    fw.handle(commands.velocity(B, 5.0))
    fw.tick(0.5)
    q_a, t_a = fw.arm.q, fw.time
    fw.tick(1.0)
    rates = (fw.arm.q - q_a) / (fw.time - t_a)
    assert rates[0] == pytest.approx(0.3, abs=0.005)
    assert rates[2] == pytest.approx(-0.5236, abs=0.005)
    assert rates[3] == pytest.approx(0.8727, abs=0.01)
    assert value(fw, E, PacketID.VELOCITY) == pytest.approx(0.3, abs=0.01)
    assert one(fw, E, PacketID.MODE).u8s() == [Mode.VELOCITY]


def test_velocity_limits_lower_the_rate(fw: Firmware) -> None:
    fw.handle(commands.limits(E, PacketID.VELOCITY_LIMITS, 0.1, -0.2))
    fw.handle(commands.velocity(E, 0.5))
    fw.tick(0.5)
    assert value(fw, E, PacketID.VELOCITY) == pytest.approx(0.1, abs=0.005)


def test_velocity_mode_stops_at_the_position_limit(fw: Firmware) -> None:
    fw.arm.reset(q=[3.0, 1.7, 3.3, 3.1])
    fw = Firmware(fw.arm)
    fw.handle(commands.velocity(C, 0.5236))
    fw.tick(1.5)
    assert 3.38 < value(fw, C, PacketID.POSITION) < 3.4034 + 0.01
    assert abs(value(fw, C, PacketID.VELOCITY)) < 0.02


def test_current_saturates_and_current_replies_report_the_drawn_current(fw: Firmware) -> None:
    fw.handle(commands.current(E, 5000.0))
    fw.tick(1.0)
    drawn = value(fw, E, PacketID.CURRENT)
    assert drawn == pytest.approx(fw.arm.current_mA[0], abs=0.01)
    # Saturated at 600 mA, then the back-EMF cuts the current near no-load speed.
    assert 0.0 < drawn < 600.0
    assert value(fw, E, PacketID.VELOCITY) > 0.9  # not rate-limited in current mode
    fw.handle(commands.current(B, -100.0))
    fw.tick(0.2)
    assert value(fw, B, PacketID.VELOCITY) < -0.1


def test_disable_and_passive_ignore_control_and_standby_holds(fw: Firmware) -> None:
    q0 = fw.arm.q
    fw.tick(2.0)  # STANDBY: D and C do not sag under gravity
    assert np.abs(fw.arm.q - q0).max() < 0.002
    fw.handle(commands.mode(D, Mode.DISABLE))
    fw.handle(commands.velocity(D, 0.5))
    fw.tick(0.5)
    assert one(fw, D, PacketID.MODE).u8s() == [Mode.DISABLE]
    assert value(fw, D, PacketID.POSITION) == pytest.approx(q0[1], abs=0.002)
    assert fw.ignored.counts["control_while_disabled"] == 1
    fw.handle(commands.mode(E, Mode.PASSIVE))
    fw.handle(commands.current(E, 300.0))
    fw.tick(0.5)
    assert value(fw, E, PacketID.CURRENT) == 0.0
    assert one(fw, E, PacketID.MODE).u8s() == [Mode.PASSIVE]


def test_position_hold_and_zero_velocity_keep_the_joint_still(fw: Firmware) -> None:
    fw.handle(commands.velocity(D, 0.4))
    fw.tick(0.5)
    fw.handle(commands.mode(D, Mode.POSITION_HOLD))
    fw.tick(0.5)
    held = value(fw, D, PacketID.POSITION)
    fw.tick(1.0)
    assert value(fw, D, PacketID.POSITION) == pytest.approx(held, abs=0.002)
    fw.handle(commands.velocity(C, -0.4))
    fw.tick(0.5)
    fw.handle(commands.mode(C, Mode.ZERO_VELOCITY))
    fw.tick(0.5)
    assert abs(value(fw, C, PacketID.VELOCITY)) < 0.01


def test_relative_position_moves_from_where_the_joint_is(fw: Firmware) -> None:
    q0 = fw.arm.q
    fw.handle(Packet(E, PacketID.RELATIVE_POSITION, pack_floats(0.2)))
    run_until(fw, lambda: abs(fw.arm.q[0] - (q0[0] + 0.2)) < 0.01, limit_s=3.0)


def test_torque_scale_slows_a_joint() -> None:
    speeds = []
    for scale in (1.0, 0.1):
        fw = Firmware(Alpha5Arm())
        fw.arm.torque_scale = [scale, 1.0, 1.0, 1.0]
        fw.handle(commands.velocity(E, 0.5))
        fw.tick(1.0)
        speeds.append(value(fw, E, PacketID.VELOCITY))
    healthy, weak = speeds
    assert healthy == pytest.approx(0.5, abs=0.01)
    assert weak < 0.6 * healthy  # 0.1 x 600 mA x 20.2 N m/A cannot beat friction + damping


# -- bad input -------------------------------------------------------------------------------
def test_empty_mode_packet_is_counted_flagged_and_harmless(fw: Firmware) -> None:
    fw.handle(commands.velocity(E, 0.2))
    empty_mode = Packet(E, PacketID.MODE, b"")  # what bytes(Mode.STANDBY) sends
    assert fw.handle(empty_mode) == []
    assert fw.errors.counts == {"bad_payload": 1}
    assert one(fw, E, PacketID.MODE).u8s() == [Mode.VELOCITY]  # unchanged
    status = HardwareStatus.from_bytes(one(fw, E, PacketID.HARDWARE_STATUS).data)
    assert HardwareStatus.SERIAL_ERROR in status
    assert fw.status(D) == HardwareStatus.NONE  # only the addressed device


def test_hardware_status_is_reported_at_1hz_while_set_then_clears(fw: Firmware) -> None:
    fw.note_link_error(CrcError(expected=0x12, actual=0x34))
    out = fw.tick(3.0)
    status = [p for p in out if p.packet_id == PacketID.HARDWARE_STATUS]
    assert [p.device_id for p in status] == [E, E, E]  # at once, then each second
    assert HardwareStatus.from_bytes(status[0].data) == HardwareStatus.CRC_ERROR
    out = fw.tick(FirmwareConfig().error_hold_s)
    assert len([p for p in out if p.packet_id == PacketID.HARDWARE_STATUS]) == 2
    assert fw.status(E) == HardwareStatus.NONE
    assert fw.tick(2.0) == []


@pytest.mark.parametrize(
    ("packet", "reason"),
    [
        (Packet(E, PacketID.POSITION, b"\x00\x00\xc0"), "bad_payload"),
        (Packet(E, PacketID.VELOCITY, pack_floats(math.nan)), "bad_value"),
        (Packet(E, PacketID.CURRENT, b""), "bad_payload"),
        (Packet(E, PacketID.MODE, b"\x02\x03"), "bad_payload"),
        (Packet(E, PacketID.MODE, b"\x7e"), "unknown_mode"),
        (Packet(E, PacketID.REQUEST, b""), "bad_payload"),
        (Packet(E, PacketID.REQUEST, bytes(range(1, 12))), "bad_payload"),
        (Packet(E, PacketID.HEARTBEAT_FREQUENCY, b""), "bad_payload"),
        (Packet(E, 0x3C, b"\x01"), "unknown_packet"),
    ],
)
def test_bad_packets_are_counted_and_the_firmware_keeps_answering(
    fw: Firmware, packet: Packet, reason: str
) -> None:
    assert fw.handle(packet) == []
    assert fw.errors.counts == {reason: 1}
    fw.tick(0.1)
    assert one(fw, E, PacketID.MODE).u8s() == [Mode.STANDBY]
    assert value(fw, E, PacketID.POSITION) == pytest.approx(fw.arm.q[0], abs=1e-6)


def test_request_with_padding_zeros_answers_the_real_ids(fw: Firmware) -> None:
    replies = fw.handle(Packet(D, PacketID.REQUEST, b"\x00\x00\x03"))
    assert [r.key for r in replies] == [(D, PacketID.POSITION)]
    # Real arms answer these at 100 Hz without a fault: padding is counted, not an error
    # (this assertion was `errors == {"bad_payload": 1}`, the emulator's old defect).
    assert fw.errors.counts == {}
    assert fw.ignored.counts == {"request_padding": 1}
    assert fw.status(D) == HardwareStatus.NONE


def test_packets_for_other_devices_and_read_only_ids_are_ignored(fw: Firmware) -> None:
    assert fw.handle(commands.position(0x06, 1.0)) == []
    assert fw.handle(Packet(E, PacketID.TEMPERATURE, pack_floats(99.0))) == []
    assert fw.ignored.counts == {"other_device": 1, "read_only": 1}
    assert fw.errors.counts == {}
    assert value(fw, E, PacketID.TEMPERATURE) == FirmwareConfig().temperature_c


# -- heartbeat, save, reset ------------------------------------------------------------------
def test_heartbeat_streams_the_chosen_packets_at_the_chosen_rate(fw: Firmware) -> None:
    fw.handle(commands.heartbeat_set(BROADCAST, [PacketID.POSITION, PacketID.VELOCITY]))
    fw.handle(commands.heartbeat_frequency(BROADCAST, 10))
    out = fw.tick(1.0)
    for dev in (A, B, C, D, E):
        assert [p.packet_id for p in out if p.device_id == dev] == [
            PacketID.POSITION,
            PacketID.VELOCITY,
        ] * 10
    ids = one(fw, D, PacketID.HEARTBEAT_SET).u8s()
    assert ids == [PacketID.POSITION, PacketID.VELOCITY] + [0] * 8
    fw.handle(commands.heartbeat_frequency(D, 0))
    assert not [p for p in fw.tick(0.5) if p.device_id == D]


def test_reset_restores_saved_settings(fw: Firmware) -> None:
    fw.handle(commands.limits(E, PacketID.CURRENT_LIMITS, 400.0, -400.0))
    fw.handle(commands.save(E))
    fw.handle(commands.limits(E, PacketID.CURRENT_LIMITS, 100.0, -100.0))
    fw.handle(commands.velocity(E, 0.2))
    fw.handle(Packet(E, PacketID.MODE, b""))  # raises the serial error flag
    fw.handle(Packet(E, PacketID.RESET, b""))
    assert one(fw, E, PacketID.CURRENT_LIMITS).floats() == [400.0, -400.0]
    assert one(fw, E, PacketID.MODE).u8s() == [Mode.STANDBY]
    assert fw.status(E) == HardwareStatus.NONE


def test_sensor_noise_changes_reports_not_the_arm() -> None:
    arm = Alpha5Arm()
    fw = Firmware(arm, FirmwareConfig(sensor_noise=SensorNoise(0.01, 0.01), seed=1))
    readings = np.array([value(fw, D, PacketID.POSITION) for _ in range(400)])
    assert readings.mean() == pytest.approx(arm.q[1], abs=0.003)
    assert readings.std() == pytest.approx(0.01, rel=0.2)


def test_scaled_sensor_noise_spreads_readings_by_the_factor() -> None:
    # A run's noise_scale multiplies both sigmas; zero reads the true state.
    rng = np.random.default_rng(3)
    q, qdot = np.zeros(2000), np.zeros(2000)
    q_n, qdot_n = SensorNoise(0.002, 0.02).scaled(2.5).apply(q, qdot, rng)
    assert q_n.std() == pytest.approx(0.005, rel=0.1)
    assert qdot_n.std() == pytest.approx(0.05, rel=0.1)
    q_0, qdot_0 = SensorNoise().scaled(0.0).apply(q, qdot, rng)
    assert not q_0.any() and not qdot_0.any()


def test_wire_bytes_of_a_reply_match_the_conformance_vector() -> None:
    # bpl-vectors.json: "SOFTWARE_VERSION 1.2.3 from device 0x02".
    fw = Firmware(Alpha5Arm(), FirmwareConfig(software_version=(1, 2, 3)))
    reply = one(fw, B, PacketID.SOFTWARE_VERSION)
    assert reply.encode() == bytes.fromhex("08 01 02 03 6C 02 07 B8 00")


# -- monitor: climate and supply -------------------------------------------------------------
def statuses(out: list[Packet], device: int) -> list[HardwareStatus]:
    return [
        HardwareStatus.from_bytes(p.data)
        for p in out
        if p.packet_id == PacketID.HARDWARE_STATUS and p.device_id == device
    ]


def test_temperature_follows_the_motor_heat_and_raises_over_temperature() -> None:
    from reach_sim_bridge.emulator.monitor import MonitorConfig

    monitor = MonitorConfig(thermal_time_constant_s=2.0, over_temperature_c=30.0)
    fw = Firmware(Alpha5Arm(), FirmwareConfig(monitor=monitor))
    fw.handle(commands.current(E, 600.0))  # runs into E's end stop, then stalls at 600 mA
    fw.tick(12.0)
    amps = fw.arm.current_mA[0] / 1000.0
    assert amps == pytest.approx(0.6, abs=0.01)
    steady = 20.0 + 10.0 * amps**2 * 3.22  # T_water + R_th I^2 R, 31.6 degC
    assert value(fw, E, PacketID.TEMPERATURE) == pytest.approx(steady, abs=0.3)
    assert value(fw, D, PacketID.TEMPERATURE) < 25.0  # D only holds against gravity
    assert HardwareStatus.OVER_TEMPERATURE in fw.status(E)
    assert HardwareStatus.OVER_TEMPERATURE not in fw.status(D)
    out = fw.tick(2.0)
    assert len(statuses(out, E)) == 2  # reported at 1 Hz while set
    fw.handle(commands.current(E, 0.0))  # cools with the same time constant
    fw.tick(12.0)
    assert value(fw, E, PacketID.TEMPERATURE) < 21.0
    assert fw.status(E) == HardwareStatus.NONE
    assert fw.errors.counts == {}


def test_voltage_sags_with_current_and_raises_low_supply_voltage() -> None:
    from reach_sim_bridge.emulator.monitor import MonitorConfig

    fw = Firmware(Alpha5Arm(), FirmwareConfig(monitor=MonitorConfig(source_resistance_ohm=10.0)))
    fw.tick(0.5)
    idle = value(fw, B, PacketID.VOLTAGE)
    assert 18.5 < idle < 24.0
    fw.handle(commands.current(E, 600.0))
    fw.tick(5.0)  # stalled at the end stop: 0.6 A more through 10 ohm
    drawn = sum(abs(i) for i in fw.arm.current_mA) / 1000.0 + abs(fw.arm.jaw_current_mA) / 1e3
    sag = value(fw, B, PacketID.VOLTAGE)
    assert sag == pytest.approx(24.0 - 10.0 * (0.1 + drawn), abs=0.05)
    assert sag < 18.0
    for dev in (A, B, C, D, E):  # one supply: every device sees it
        assert HardwareStatus.LOW_SUPPLY_VOLTAGE in fw.status(dev)
        assert value(fw, dev, PacketID.VOLTAGE) == pytest.approx(sag)
    fw.handle(commands.current(E, 0.0))
    fw.tick(1.0)
    assert value(fw, B, PacketID.VOLTAGE) > 18.5
    assert all(fw.status(dev) == HardwareStatus.NONE for dev in (A, B, C, D, E))


def test_a_leak_raises_humidity_and_pressure_of_that_device_only() -> None:
    from reach_sim_bridge.emulator.faults import Leak

    fw = Firmware(Alpha5Arm(), FirmwareConfig(leaks=(Leak(D, time_constant_s=4.0, depth_m=10),)))
    out = fw.tick(12.0)  # three time constants
    humidity = value(fw, D, PacketID.HUMIDITY)
    assert humidity == pytest.approx(100.0 - 90.0 * math.exp(-3.0), abs=0.5)
    pressure = value(fw, D, PacketID.INTERNAL_PRESSURE)
    assert 1.8 < pressure < 2.1  # towards 1.013 + 10 m x 0.1006 bar/m
    assert HardwareStatus.OVER_HUMIDITY in fw.status(D)
    assert HardwareStatus.OVER_PRESSURE in fw.status(D)
    assert statuses(out, D) and not statuses(out, C)
    assert value(fw, C, PacketID.HUMIDITY) == pytest.approx(10.0)
    assert value(fw, C, PacketID.INTERNAL_PRESSURE) == pytest.approx(1.0, abs=0.01)
    # FACTORY_CLIMATE is what was measured at assembly: the leak does not change it.
    assert one(fw, D, PacketID.FACTORY_CLIMATE).floats() == pytest.approx([20.0, 1.0, 10.0])
    fw.handle(Packet(D, PacketID.RESET, b""))  # a RESET does not stop water
    fw.tick(0.1)
    assert HardwareStatus.OVER_HUMIDITY in fw.status(D)


def test_a_leak_can_be_injected_at_run_time(fw: Firmware) -> None:
    from reach_sim_bridge.emulator.faults import Leak

    fw.tick(1.0)
    assert fw.status(B) == HardwareStatus.NONE
    fw.inject_leak(Leak(B, time_constant_s=1.0))
    fw.tick(2.0)
    assert HardwareStatus.OVER_HUMIDITY in fw.status(B)
    fw.stop_leak(B)
    humidity = value(fw, B, PacketID.HUMIDITY)
    fw.tick(1.0)
    assert value(fw, B, PacketID.HUMIDITY) == pytest.approx(humidity)  # no drying out


def test_pressure_follows_temperature_in_a_sealed_housing() -> None:
    from reach_sim_bridge.emulator.monitor import Monitor, MonitorConfig

    monitor = Monitor(MonitorConfig(thermal_time_constant_s=1.0), [3.22], 20.0, 24.0)
    for _ in range(1000):
        monitor.step(0.01, [1.0], 24.0)
    t = monitor.temperature_c[0]
    assert t == pytest.approx(20.0 + 10.0 * 3.22, abs=0.01)
    assert monitor.pressure_bar(0) == pytest.approx((t + 273.15) / 293.15, rel=1e-6)
    assert monitor.voltage_v == pytest.approx(24.0 - 1.0 * 1.1, abs=1e-6)


# -- end-effector moves (KM_END_POS, KM_END_VEL on the base device) --------------------------
def end_pos(device: int, *pose: float) -> Packet:
    return Packet(device, PacketID.KM_END_POS, pack_floats(*pose))


def test_a_reachable_end_pose_is_reached_within_5_mm(fw: Firmware) -> None:
    goal_q = fw.arm.q + np.array([0.5, -0.4, 0.3, 0.6])
    goal = fw.arm.pose_at(goal_q)  # reachable by construction
    assert fw.handle(end_pos(E, *goal)) == []
    assert fw.ignored.counts == {} and fw.errors.counts == {}
    assert [one(fw, d, PacketID.MODE).u8s() for d in (E, D, C, B)] == [[Mode.POSITION]] * 4
    fw.tick(3.0)  # the largest move is 0.6 rad at 0.87 rad/s, 0.5 at 0.52
    reached = fw.arm.pose_at(fw.arm.q)  # FK of the arm's angles after settling
    assert math.dist(reached[:3], goal[:3]) < 5.0
    reported = one(fw, E, PacketID.KM_END_POS).floats()
    assert math.dist(reported[:3], goal[:3]) < 5.0
    assert reported[3:] == pytest.approx(goal[3:], abs=0.02)  # the roll too
    assert np.abs(fw.arm.qdot).max() < 0.01


def test_an_unreachable_end_pose_is_refused_with_no_motion(fw: Firmware) -> None:
    q0 = fw.arm.q
    assert fw.handle(end_pos(E, 1000.0, 0.0, 0.0, 0.0, 0.0, 0.0)) == []  # 1 m: beyond reach
    assert fw.ignored.counts == {"unreachable_pose": 1}
    assert fw.errors.counts == {}
    fw.tick(1.0)
    assert np.abs(fw.arm.q - q0).max() < 0.002
    assert [one(fw, d, PacketID.MODE).u8s() for d in (E, D, C, B)] == [[Mode.STANDBY]] * 4
    assert fw.status(E) == HardwareStatus.NONE


def test_end_moves_go_to_the_base_device_only(fw: Firmware) -> None:
    pose = fw.arm.end_effector_pose()
    assert fw.handle(end_pos(D, *pose)) == []
    assert fw.ignored.counts == {"not_the_base_device": 1}
    assert fw.handle(Packet(E, PacketID.KM_END_POS, pack_floats(1.0, 2.0))) == []
    assert fw.errors.counts == {"bad_payload": 1}


def test_a_cartesian_velocity_moves_the_tool_in_a_straight_line(fw: Firmware) -> None:
    start = fw.arm.end_effector_pose()
    fw.handle(Packet(E, PacketID.KM_END_VEL, pack_floats(0.0, 0.0, 20.0, 0.0, 0.0, 0.0)))
    fw.tick(1.0)
    moved = np.subtract(fw.arm.end_effector_pose()[:3], start[:3])
    assert moved[2] == pytest.approx(20.0, abs=3.0)  # 20 mm/s up, for 1 s (less the ramp)
    assert np.hypot(moved[0], moved[1]) < 2.0
    velocity = one(fw, E, PacketID.KM_END_VEL).floats()
    assert velocity[:3] == pytest.approx([0.0, 0.0, 20.0], abs=1.0)
    fw.handle(Packet(E, PacketID.KM_END_VEL, bytes(24)))  # zero: stop
    fw.tick(0.5)
    assert np.abs(fw.arm.qdot).max() < 0.01
    # A joint command takes the arm back from Cartesian control.
    fw.handle(Packet(E, PacketID.KM_END_VEL, pack_floats(0.0, 0.0, 20.0, 0.0, 0.0, 0.0)))
    fw.tick(0.2)
    fw.handle(commands.velocity(D, 0.0))
    fw.tick(0.5)
    assert abs(fw.arm.qdot[0]) < 0.01 and abs(fw.arm.qdot[1]) < 0.01


def test_a_cartesian_velocity_is_kept_inside_the_joint_rate_limits(fw: Firmware) -> None:
    fw.handle(Packet(E, PacketID.KM_END_VEL, pack_floats(0.0, 0.0, 2000.0, 0.0, 0.0, 0.0)))
    fw.tick(1.0)
    rates = np.abs(fw.arm.qdot)
    assert np.all(rates <= np.array([RATE[E], RATE[D], RATE[C], RATE[B]]) + 0.02)
    assert rates.max() > 0.4  # and it does move, at the fastest joint's limit


def test_half_duplex_broadcast_requests_collide() -> None:
    fw = Firmware(Alpha5Arm(), FirmwareConfig(half_duplex=True))
    assert ask(fw, BROADCAST, PacketID.POSITION) == []  # five devices talk at once
    assert fw.ignored.counts == {"broadcast_collision": 1}
    assert [r.device_id for r in ask(fw, BROADCAST, PacketID.KM_END_POS)] == [E]  # one talker
    assert [r.key for r in ask(fw, D, PacketID.POSITION)] == [(D, PacketID.POSITION)]
    assert fw.errors.counts == {}


def test_zero_velocity_after_a_stall_at_the_end_stop_bleeds_the_stall_current() -> None:
    """A3-13: 600 mA into E's end stop, then the safe stop (ZERO_VELOCITY). The switch is
    bumpless (the integral starts at the applied current) and the joint cannot move, so the
    error stays zero; the anti-windup must bleed the integral instead of holding 600 mA."""
    fw = Firmware(Alpha5Arm())
    fw.handle(commands.current(E, 600.0))
    run_until(fw, lambda: value(fw, E, PacketID.POSITION) >= 6.143 - 1e-3, limit_s=30.0)
    fw.tick(1.0)  # stalled against the stop
    assert value(fw, E, PacketID.CURRENT) == pytest.approx(600.0, abs=10.0)
    fw.handle(commands.mode(E, Mode.ZERO_VELOCITY))
    stop = value(fw, E, PacketID.POSITION)
    fw.tick(2.0)  # ten bleed time constants of arm time
    assert abs(value(fw, E, PacketID.CURRENT)) < 20.0
    assert value(fw, E, PacketID.POSITION) == pytest.approx(stop, abs=0.01)  # still held
    assert one(fw, E, PacketID.MODE).u8s() == [Mode.ZERO_VELOCITY]


def test_velocity_into_the_limit_does_not_wind_up_and_d_still_holds_against_gravity() -> None:
    """The bleed acts only on a push into a limit or a stall: D holding against gravity in
    ZERO_VELOCITY keeps its integral (it does not sag), and a velocity command into C's
    limit leaves no stored current once it sits at the limit."""
    fw = Firmware(Alpha5Arm())
    fw.handle(commands.velocity(D, 0.4))
    fw.tick(0.5)
    fw.handle(commands.mode(D, Mode.ZERO_VELOCITY))
    fw.tick(0.5)
    held = value(fw, D, PacketID.POSITION)
    fw.tick(5.0)
    assert value(fw, D, PacketID.POSITION) == pytest.approx(held, abs=0.002)
    fw.handle(commands.velocity(C, -0.5))
    run_until(fw, lambda: value(fw, C, PacketID.POSITION) <= 0.0175 + 1e-3, limit_s=30.0)
    fw.tick(2.0)
    assert abs(value(fw, C, PacketID.CURRENT)) < 1.0  # 40 mA kept pushing outward without it


def test_a_stall_at_full_current_derates_the_limit_and_rest_restores_it() -> None:
    """Thermal derating (reach_sim_bridge/emulator/derating.py, assumed constants): E held
    at 600 mA against its end stop for a minute of arm time heats its winding estimate, so
    the firmware lowers the limit and the CURRENT it reports falls to the continuous 400 mA
    while the set limit stays as set; the housing's TEMPERATURE has risen with it. After
    half a minute at rest the full 600 mA is back."""
    fw = Firmware(Alpha5Arm())
    fw.handle(commands.current(E, 600.0))
    fw.tick(5.0)  # from its start into the stop
    assert value(fw, E, PacketID.POSITION) == pytest.approx(6.143, abs=0.01)
    assert value(fw, E, PacketID.CURRENT) == pytest.approx(600.0, abs=5.0)
    fw.tick(55.0)
    assert value(fw, E, PacketID.CURRENT) == pytest.approx(400.0, abs=5.0)  # derated
    assert one(fw, E, PacketID.CURRENT_LIMITS).floats() == pytest.approx([600.0, -600.0])
    hot = value(fw, E, PacketID.TEMPERATURE)
    assert hot > 22.0  # 20 degC water; D, not pushed, stays cool
    assert value(fw, D, PacketID.TEMPERATURE) < 21.0
    assert value(fw, D, PacketID.CURRENT) < 200.0  # only its gravity load: not derated
    fw.handle(commands.current(E, 0.0))
    fw.tick(30.0)  # rest: the estimate cools below the derating's start
    assert value(fw, E, PacketID.TEMPERATURE) < hot
    fw.handle(commands.current(E, 600.0))
    fw.tick(0.5)
    assert value(fw, E, PacketID.CURRENT) == pytest.approx(600.0, abs=5.0)


def test_the_derated_limit_caps_the_velocity_loop_and_derating_can_be_turned_off() -> None:
    """The derated limit caps the velocity loop's output as it caps current mode: with a
    continuous rating of 60 mA on E (a knob of `CurrentDerating`), a minute at 600 mA leaves
    E unable to draw the ~95 mA that 0.5 rad/s needs, so it moves slower, at 60 mA.
    `FirmwareConfig(derating=None)` is the underated firmware."""
    from reach_sim_bridge.emulator.derating import CurrentDerating

    weak = FirmwareConfig(derating=CurrentDerating(continuous_fraction=0.1))
    for config, speed, current in ((weak, 0.2, 60.0), (FirmwareConfig(derating=None), 0.49, 95)):
        fw = Firmware(Alpha5Arm(), config)
        fw.handle(commands.current(E, 600.0))
        fw.tick(60.0)
        fw.handle(commands.velocity(E, -0.5))  # out of the stop
        fw.tick(2.0)
        assert -value(fw, E, PacketID.VELOCITY) == pytest.approx(speed, abs=0.05)
        assert -value(fw, E, PacketID.CURRENT) == pytest.approx(current, abs=5.0)
