"""HARDWARE_STATUS by name, which flags block a joint, and the Monitor readings, against the
virtual arm (docs/protocol.md sections 3a and 8; the policy is in reach_driver/faults.py)."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from conftest import wait_until

from protocol import DeviceID, HardwareStatus, Mode, PacketID
from reach_driver import ArmClient, open_transport
from reach_driver.cli import Exit, main
from reach_driver.errors import ArmFaultError
from reach_driver.faults import (
    BLOCKING_FLAGS,
    FLAG_POLICY,
    LINK_ERROR_FLAGS,
    blocking_flags,
    status_bytes,
)
from reach_sim_bridge.emulator.faults import Leak
from reach_sim_bridge.emulator.firmware import FirmwareConfig
from reach_sim_bridge.emulator.monitor import MONITOR_FLAGS, MonitorConfig
from reach_sim_bridge.emulator.server import SimServer

SPEED = 4.0
NAMED = [f for f in HardwareStatus if f.value and f.name]


pytestmark = pytest.mark.sim(speed=SPEED)


def _client(server: SimServer) -> ArmClient:
    return ArmClient(open_transport(str(server.link))).start()


# ------------------------------------------------------------------ the policy, by name


def test_every_named_flag_has_a_policy_with_a_reason() -> None:
    assert set(FLAG_POLICY) == set(NAMED)
    for flag, (blocks, why) in FLAG_POLICY.items():
        assert isinstance(blocks, bool) and len(why) > 20, flag
        assert bool(flag & BLOCKING_FLAGS) == blocks, flag
    assert not BLOCKING_FLAGS & LINK_ERROR_FLAGS


@pytest.mark.parametrize(
    "flag",
    [
        HardwareStatus.ENCODER_FAULT,
        HardwareStatus.ENCODER_POSITION_INVALID,
        HardwareStatus.INVALID_FIRMWARE,
        HardwareStatus.OVER_TEMPERATURE,
        HardwareStatus.MOTOR_OVER_CURRENT,
    ],
)
def test_the_briefs_blocking_examples_block(flag: HardwareStatus) -> None:
    assert blocking_flags(flag) == flag


@pytest.mark.parametrize(
    "flag",
    [
        HardwareStatus.READ_PROTECTION_ENABLED,
        HardwareStatus.JOINT_SERVICE_DUE,
        HardwareStatus.JAW_ZERO_REQUIRED,
        HardwareStatus.SERIAL_ERROR,
        HardwareStatus.CRC_ERROR,
    ],
)
def test_informational_flags_do_not_block(flag: HardwareStatus) -> None:
    assert blocking_flags(flag) == HardwareStatus.NONE


def test_an_unnamed_bit_blocks_because_its_meaning_is_unknown() -> None:
    assert blocking_flags(HardwareStatus(0x40)) == HardwareStatus(0x40)  # byte D, reserved


def test_status_bytes_names_every_byte() -> None:
    flags = (
        HardwareStatus.OVER_HUMIDITY
        | HardwareStatus.OVER_PRESSURE
        | HardwareStatus.JAW_ZERO_REQUIRED
        | HardwareStatus.JOINT_SERVICE_DUE
        | HardwareStatus.READ_PROTECTION_ENABLED
        | HardwareStatus.ENCODER_FAULT
        | HardwareStatus.ENCODER_POSITION_INVALID
        | HardwareStatus.LOW_SUPPLY_VOLTAGE
        | HardwareStatus.INVALID_FIRMWARE
        | HardwareStatus.CAN_BUS_ERROR
        | HardwareStatus.POSITION_REPORT_NOT_RECEIVED
        | HardwareStatus(0x20 << 8)  # byte C, reserved
    )
    assert status_bytes(flags) == {
        "A": ["OVER_HUMIDITY"],
        "B": ["OVER_PRESSURE"],
        "C": [  # in bit order, from the top bit
            "bit 0x20",
            "JAW_ZERO_REQUIRED",
            "JOINT_SERVICE_DUE",
            "READ_PROTECTION_ENABLED",
            "ENCODER_FAULT",
        ],
        "D": [
            "ENCODER_POSITION_INVALID",
            "LOW_SUPPLY_VOLTAGE",
            "INVALID_FIRMWARE",
            "CAN_BUS_ERROR",
            "POSITION_REPORT_NOT_RECEIVED",
        ],
    }
    assert status_bytes(HardwareStatus.NONE) == {"A": [], "B": [], "C": [], "D": []}


# ------------------------------------------------------------------ on the virtual arm


def _wait_flag(client: ArmClient, device: int, flag: HardwareStatus) -> None:
    def seen() -> bool:
        client.read_status([device])
        status = client.joint(device).status
        return status is not None and bool(status.value & flag)

    assert wait_until(seen, timeout=5.0), f"{flag.name} never reported"


INJECTABLE = [f for f in NAMED if not f & MONITOR_FLAGS]  # the monitor model owns the rest


@pytest.mark.parametrize("flag", INJECTABLE, ids=lambda f: f.name)
def test_an_injected_flag_blocks_the_joint_or_not_as_the_policy_says(
    sim: SimServer, flag: HardwareStatus
) -> None:
    with _client(sim) as client:
        device = int(DeviceID.C)
        here = float(client.read_joints((PacketID.POSITION,)).q[2])
        sim.inject_fault(device, flag)
        _wait_flag(client, device, flag)
        if FLAG_POLICY[flag][0]:
            with pytest.raises(ArmFaultError) as err:
                client.command_position(device, here)
            message = str(err.value)
            assert flag.name is not None  # a single flag: named
            assert flag.name in message and "C (0x03)" in message
            assert "nothing was sent" in message
            with pytest.raises(ArmFaultError):
                client.command_velocity(device, 0.1)
            with pytest.raises(ArmFaultError):
                client.set_mode(device, Mode.CURRENT)
            assert sim.firmware.mode(device) == Mode.STANDBY  # nothing reached it
            client.set_mode(device, Mode.ZERO_VELOCITY)  # a safe mode always goes out
            client.command_position(DeviceID.E, float(client.state.q[0]))  # E is healthy
            assert client.blocking_faults() == {device: [flag.name]}
        else:
            client.command_position(device, here)
            assert wait_until(lambda: sim.firmware.mode(device) == Mode.POSITION)
            assert client.blocking_faults() == {}


@pytest.mark.parametrize(
    ("firmware", "flag"),
    [
        (FirmwareConfig(temperature_c=70.0), HardwareStatus.OVER_TEMPERATURE),
        (
            FirmwareConfig(monitor=MonitorConfig(low_voltage_v=26.0)),
            HardwareStatus.LOW_SUPPLY_VOLTAGE,
        ),
    ],
    ids=["over-temperature", "low-supply-voltage"],
)
def test_monitor_flags_block(sim_factory, firmware: FirmwareConfig, flag: HardwareStatus) -> None:
    sim = sim_factory(speed=SPEED, firmware=firmware)
    with _client(sim) as client:
        _wait_flag(client, int(DeviceID.D), flag)
        with pytest.raises(ArmFaultError, match=flag.name):
            client.command_positions(client.read_joints((PacketID.POSITION,)).q)


def test_info_json_names_the_flags_of_every_byte(sim, capsys) -> None:
    sim.inject_fault(int(DeviceID.D), HardwareStatus.READ_PROTECTION_ENABLED)
    sim.inject_fault(int(DeviceID.D), HardwareStatus.ENCODER_POSITION_INVALID)
    sim.inject_fault(int(DeviceID.B), HardwareStatus.JOINT_SERVICE_DUE)
    code = main(["--port", str(sim.link), "info", "--json"])
    out = capsys.readouterr().out
    assert code == Exit.OK, out
    devices = json.loads(out)["devices"]
    d = devices["D"]
    assert d["status"]["C"] == ["READ_PROTECTION_ENABLED"]
    assert d["status"]["D"] == ["ENCODER_POSITION_INVALID"]
    assert d["status"]["A"] == [] and d["status"]["B"] == []
    assert d["blocking_flags"] == ["ENCODER_POSITION_INVALID"]
    assert devices["B"]["status"]["C"] == ["JOINT_SERVICE_DUE"]
    assert devices["B"]["blocking_flags"] == []
    assert devices["E"]["blocking_flags"] == []


def test_info_table_shows_flags_by_byte(sim, capsys) -> None:
    sim.inject_fault(int(DeviceID.C), HardwareStatus.CAN_BUS_ERROR)
    sim.inject_fault(int(DeviceID.C), HardwareStatus.JAW_ZERO_REQUIRED)
    assert main(["--port", str(sim.link), "info"]) == Exit.OK
    out = capsys.readouterr().out
    assert "D: CAN_BUS_ERROR" in out and "C: JAW_ZERO_REQUIRED" in out


# ------------------------------------------------------------------ Monitor readings

ALL = [int(d) for d in (DeviceID.E, DeviceID.D, DeviceID.C, DeviceID.B, DeviceID.A)]


def test_read_diagnostics_gives_plausible_readings_of_every_device(sim) -> None:
    with _client(sim) as client:
        got = client.read_diagnostics()
    assert sorted(got) == sorted(ALL)
    for dev, js in got.items():
        assert js.voltage is not None and js.temperature is not None, dev
        assert js.humidity is not None and js.internal_pressure is not None, dev
        assert js.factory_climate is not None and js.status is not None, dev
        values = [js.voltage.value, js.temperature.value, js.humidity.value]
        values += [js.internal_pressure.value, *js.factory_climate.value]
        assert all(math.isfinite(v) for v in values), dev
        assert 18.0 <= js.voltage.value <= 30.0  # the rated supply range
        assert 0.0 <= js.temperature.value <= 60.0
        assert 0.0 <= js.humidity.value <= 40.0
        assert 0.8 <= js.internal_pressure.value <= 1.3
        climate = js.factory_climate.value
        assert climate.temperature_c == pytest.approx(20.0)
        assert climate.pressure_bar == pytest.approx(1.0)
        assert climate.humidity_pct == pytest.approx(10.0)
        assert js.status.value == HardwareStatus.NONE


def test_a_leak_shows_as_rising_humidity_and_the_over_humidity_flag(sim_factory) -> None:
    sim = sim_factory(speed=8.0)
    device = int(DeviceID.D)
    with _client(sim) as client:
        before = client.read_diagnostics([device])[device].humidity
        assert before is not None and before.value == pytest.approx(10.0)
        # tau 5 s: the humidity crosses the 40 % level after 0.4 tau, 2 s of sim time
        sim.observe(lambda arm, fw: fw.inject_leak(Leak(device, time_constant_s=5.0)))
        seen: list[float] = []

        def flagged() -> bool:
            js = client.read_diagnostics([device])[device]
            assert js.humidity is not None and js.status is not None
            seen.append(js.humidity.value)
            return bool(js.status.value & HardwareStatus.OVER_HUMIDITY)

        assert wait_until(flagged, timeout=10.0, poll_s=0.05)
        assert seen[-1] > 40.0
        assert np.all(np.diff(seen) >= 0.0) and seen[-1] > seen[0]
        assert "OVER_HUMIDITY" in client.blocking_faults()[device]
        with pytest.raises(ArmFaultError, match="OVER_HUMIDITY"):
            client.command_position(device, float(client.read_joints().q[1]))
        others = client.read_diagnostics([int(DeviceID.E)])[int(DeviceID.E)]
        assert others.humidity is not None and others.humidity.value < 11.0  # E is dry


def test_pressure_0x6e_is_decoded_and_tracked_apart_from_0x67() -> None:
    """The newest SDK's PRESSURE (0x6E) lands in JointState.pressure, 0x67 stays where it was:
    a firmware answering 0x67 as DEVICE_TYPE cannot overwrite the 0x6E pressure."""
    from protocol import Packet
    from protocol.payload import pack_floats
    from reach_driver.queries import DIAGNOSTICS
    from reach_driver.state import StateTable, packet_value

    assert PacketID.PRESSURE == 0x6E and PacketID.PRESSURE in DIAGNOSTICS
    table = StateTable()
    assert table.update(Packet(DeviceID.D, 0x6E, pack_floats(1.25)), t=1.0)
    assert table.update(Packet(DeviceID.D, 0x67, bytes.fromhex("00 00 80 3f")), t=2.0)
    js = table.get(DeviceID.D)
    assert js.pressure is not None and js.pressure.value == pytest.approx(1.25)
    assert js.pressure.t == 1.0
    assert js.internal_pressure is not None and js.internal_pressure.value == 1.0
    assert packet_value(Packet(DeviceID.D, 0x6E, pack_floats(0.5))) == pytest.approx(0.5)
    assert not table.update(Packet(DeviceID.D, 0x6E, b"\x01"), t=3.0)  # not a float
    assert table.bad_payloads == 1


def test_the_virtual_arms_0x6e_pressure_reaches_info_json(sim, capsys) -> None:
    with _client(sim) as client:
        got = client.read_diagnostics([int(DeviceID.C)])[int(DeviceID.C)]
    assert got.pressure is not None and got.internal_pressure is not None
    assert got.pressure.value == pytest.approx(got.internal_pressure.value, abs=1e-3)
    assert main(["--port", str(sim.link), "info", "--json"]) == Exit.OK
    diag = json.loads(capsys.readouterr().out)["devices"]["C"]["diagnostics"]
    assert diag["pressure_0x6e_bar"] == pytest.approx(1.0, abs=0.1)


def test_info_json_and_table_show_the_diagnostics_with_units(sim, capsys) -> None:
    assert main(["--port", str(sim.link), "info", "--json"]) == Exit.OK
    devices = json.loads(capsys.readouterr().out)["devices"]
    diag = devices["C"]["diagnostics"]
    assert 18.0 <= diag["voltage_v"] <= 30.0
    assert diag["temperature_c"] == pytest.approx(20.0, abs=5.0)
    assert diag["humidity_pct"] == pytest.approx(10.0, abs=1.0)
    assert diag["internal_pressure_bar"] == pytest.approx(1.0, abs=0.1)
    assert diag["factory_climate"] == {
        "temperature_c": pytest.approx(20.0),
        "pressure_bar": pytest.approx(1.0),
        "humidity_pct": pytest.approx(10.0),
    }
    assert main(["--port", str(sim.link), "info"]) == Exit.OK
    out = capsys.readouterr().out
    for unit in ("V", "degC", "%", "bar"):
        assert unit in out
    # 24 V less the electronics' 0.1 A and the holding currents through the 1 ohm source
    assert re.search(r" 2[0-4]\.\d\d ", out)


def test_monitor_shows_diagnostics_and_status(sim, capsys) -> None:
    sim.inject_fault(int(DeviceID.B), HardwareStatus.JOINT_SERVICE_DUE)
    assert main(["--port", str(sim.link), "monitor", "--seconds", "1.2"]) == Exit.OK
    out = capsys.readouterr().out
    for column in ("supply V", "temp degC", "RH %", "0x67 bar", "0x6E bar", "status"):
        assert column in out
    assert re.search(r" 2[0-4]\.\d\d ", out)  # the supply, sagging with the motors' current
    assert "C: JOINT_SERVICE_DUE" in out
