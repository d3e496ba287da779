"""Command builders, payload helpers, ids and the Packet value type."""

from __future__ import annotations

import dataclasses
import math

import pytest

from protocol import (
    DeviceID,
    HardwareStatus,
    Mode,
    Packet,
    PacketID,
    PayloadError,
    alpha5,
    commands,
    decode_packet,
    encode_packet,
    payload,
)


def _wire(text: str) -> bytes:
    return bytes.fromhex(text)


def test_builders_match_vectors() -> None:
    assert commands.position(0x01, 1.5).encode() == _wire("01 01 07 C0 3F 03 01 08 CB 00")
    assert commands.request(0x01, [PacketID.POSITION]).encode() == _wire("06 03 60 01 05 52 00")
    assert commands.request(DeviceID.BROADCAST, [3, 2]).encode() == _wire("07 03 02 60 FF 06 0B 00")
    assert commands.mode(0xFF, Mode.VELOCITY).encode() == _wire("06 03 01 FF 05 D8 00")
    assert commands.mode(DeviceID.E, Mode.STANDBY).encode() == _wire("01 05 01 05 05 BD 00")
    assert commands.velocity(0x05, 0.0).encode() == _wire("01 01 01 01 05 02 05 08 B6 00")
    assert commands.heartbeat_frequency(0xFF, 10).encode() == _wire("06 0A 92 FF 05 CA 00")


def test_mode_payload_is_one_byte() -> None:
    packet = commands.mode(5, Mode.STANDBY)
    assert packet.data == b"\x00"
    assert packet.as_u8() == Mode.STANDBY
    assert Mode.STANDBY.payload() == b"\x00"
    assert bytes(Mode.STANDBY) == b""  # the trap the builder avoids
    assert commands.mode(5, 0x99).data == b"\x99"  # undocumented modes pass through
    for bad in (-1, 256, 2.0, None, True):
        with pytest.raises(PayloadError, match="mode must be"):
            commands.mode(5, bad)  # type: ignore[arg-type]


def test_float_commands() -> None:
    assert commands.current(4, 250.0).floats() == [250.0]
    assert commands.current(4, 250).packet_id is PacketID.CURRENT
    assert commands.velocity(2, -0.5).as_float() == -0.5
    assert commands.position(3, 2).data == _wire("00 00 00 40")
    for builder in (commands.position, commands.velocity, commands.current):
        for bad in (math.nan, math.inf, -math.inf):
            with pytest.raises(PayloadError, match="must be finite"):
                builder(1, bad)
        with pytest.raises(PayloadError, match="must be a number"):
            builder(1, "1.0")  # type: ignore[arg-type]
    with pytest.raises(PayloadError, match="float32 range"):
        commands.current(1, 1e39)


def test_request_validation() -> None:
    assert commands.request(1, iter([3, 2, 5])).data == b"\x03\x02\x05"
    assert len(commands.request(1, range(1, 11)).data) == 10
    with pytest.raises(PayloadError, match="1 to 10 packet ids, got 0"):
        commands.request(1, [])
    with pytest.raises(PayloadError, match="1 to 10 packet ids, got 11"):
        commands.request(1, range(1, 12))
    with pytest.raises(PayloadError, match="0 is padding"):
        commands.request(1, [0, 3])
    with pytest.raises(PayloadError, match="got 256"):
        commands.request(1, [256])
    with pytest.raises(PayloadError, match="list of packet ids"):
        commands.request(1, b"\x03")


def test_heartbeat_set_pads_to_ten() -> None:
    packet = commands.heartbeat_set(0xFF, [PacketID.POSITION, PacketID.VELOCITY])
    assert packet.data == b"\x03\x02" + bytes(8)
    assert packet.packet_id == 0x91
    assert commands.heartbeat_set(0xFF, []).data == bytes(10)
    with pytest.raises(PayloadError, match="0 to 10 packet ids, got 11"):
        commands.heartbeat_set(0xFF, range(1, 12))
    with pytest.raises(PayloadError, match="0 is padding"):
        commands.heartbeat_set(0xFF, [3, 0])


def test_heartbeat_frequency_range() -> None:
    assert commands.heartbeat_frequency(1, 0).data == b"\x00"
    assert commands.heartbeat_frequency(1, 255).data == b"\xff"
    for bad in (-1, 256, 10.0, True):
        with pytest.raises(PayloadError, match="heartbeat frequency"):
            commands.heartbeat_frequency(1, bad)  # type: ignore[arg-type]


def test_limits_order_is_max_min() -> None:
    packet = commands.limits(5, PacketID.CURRENT_LIMITS, 600.0, -600.0)
    assert packet.packet_id == 0x12
    assert packet.floats() == [600.0, -600.0]
    assert commands.limits(5, 0x10, 6.1, 0.0175).floats() == pytest.approx([6.1, 0.0175])
    with pytest.raises(PayloadError, match="below minimum"):
        commands.limits(5, PacketID.POSITION_LIMITS, 0.0, 3.0)
    with pytest.raises(PayloadError, match="POSITION_LIMITS, VELOCITY_LIMITS or CURRENT_LIMITS"):
        commands.limits(5, PacketID.POSITION, 1.0, 0.0)
    with pytest.raises(PayloadError, match="finite"):
        commands.limits(5, PacketID.VELOCITY_LIMITS, math.nan, 0.0)


def test_save() -> None:
    assert commands.save(3) == Packet(3, PacketID.SAVE, b"\x00")


def test_payload_helpers() -> None:
    assert payload.pack_floats(1.0) == _wire("00 00 80 3F")  # little-endian always
    assert payload.pack_floats(1.0, -2.0) == _wire("00 00 80 3F 00 00 00 C0")
    assert payload.pack_floats() == b""
    assert payload.unpack_floats(_wire("00 00 80 3F 00 00 00 C0")) == [1.0, -2.0]
    assert payload.unpack_floats(bytearray(4)) == [0.0]
    with pytest.raises(PayloadError, match="multiple of 4"):
        payload.unpack_floats(b"12345")
    with pytest.raises(PayloadError, match="cannot pack"):
        payload.pack_floats("x")  # type: ignore[arg-type]
    assert payload.pack_u8s(1, 2, 255) == b"\x01\x02\xff"
    assert payload.unpack_u8s(b"\x01\x02") == [1, 2]
    for bad in (256, -1, 1.0, True):
        with pytest.raises(PayloadError, match="u8 values"):
            payload.pack_u8s(bad)  # type: ignore[arg-type]


FACT_SHEET_PACKET_IDS = (
    [0x01, 0x02, 0x03, 0x05, 0x0D, 0x0E, 0x10, 0x11, 0x12, 0x50, 0x60, 0x61, 0x62, 0x64]
    + [0x65, 0x66, 0x67, 0x68, 0x6C, 0x6E, 0x90, 0x91, 0x92, 0xA1, 0xA2, 0xFD]
    + list(range(0x55, 0x5F))
    + list(range(0xA5, 0xAF))
    + [0xAF, 0xB1, 0xD8, 0x99, 0xFF]
)


def test_every_fact_sheet_id_is_named() -> None:
    for value in FACT_SHEET_PACKET_IDS:
        assert PacketID(value).value == value
    assert PacketID.DEVICE_TYPE is PacketID.INTERNAL_PRESSURE
    assert [int(d) for d in alpha5.JOINTS] == [0x05, 0x04, 0x03, 0x02]
    assert DeviceID.JAWS is DeviceID.A and DeviceID.BASE_ROTATE is DeviceID.E
    assert {int(d) for d in (DeviceID.F, DeviceID.G, DeviceID.ROUTER, DeviceID.COMPUTE)} == {
        0x06,
        0x07,
        0x0D,
        0x0E,
    }
    assert DeviceID.BROADCAST == 0xFF
    assert [int(m) for m in Mode] == [0x00, 0x01, 0x02, 0x03, 0x04, 0x15, 0x1D, 0x26]


def test_unknown_ids_decode_as_plain_ints() -> None:
    packet = decode_packet(encode_packet(0x42, 0x77, b"\x01"))
    assert type(packet.device_id) is int and packet.device_id == 0x42
    assert type(packet.packet_id) is int and packet.packet_id == 0x77
    known = decode_packet(encode_packet(5, 3, bytes(4)))
    assert known.device_id is DeviceID.E and known.packet_id is PacketID.POSITION


def test_hardware_status_flags() -> None:
    status = HardwareStatus.from_bytes(bytes([0x81, 0x40, 0x00, 0x64]))
    assert HardwareStatus.FLASH_READ_FAILED in status
    assert HardwareStatus.ENCODER_NOT_DETECTED in status
    assert HardwareStatus.MOTOR_NOT_CONNECTED in status
    assert HardwareStatus.OVER_HUMIDITY not in status
    assert status.flag_names() == [
        "FLASH_READ_FAILED",
        "ENCODER_NOT_DETECTED",
        "MOTOR_NOT_CONNECTED",
    ]
    assert status.to_bytes() == bytes([0x81, 0x40, 0x00, 0x64])  # reserved bits kept
    assert HardwareStatus.from_bytes(bytes(4)) == HardwareStatus.NONE
    assert (HardwareStatus.DRIVER_OVER_TEMPERATURE | HardwareStatus.CRC_ERROR).to_bytes() == (
        bytes([0x08, 0x01, 0x00, 0x00])
    )
    with pytest.raises(PayloadError, match="must be 4 bytes, got 3"):
        HardwareStatus.from_bytes(b"\x00\x00\x00")
    # Bytes A and B (16 flags) and the documented bits of bytes C (4) and D (5).
    assert len({f.value for f in HardwareStatus if f.value}) == 25


#: Bytes C and D of HARDWARE_STATUS by name: (byte index, bit, name).
STATUS_C_D = [
    (2, 0x10, "JAW_ZERO_REQUIRED"),
    (2, 0x08, "JOINT_SERVICE_DUE"),
    (2, 0x04, "READ_PROTECTION_ENABLED"),
    (2, 0x02, "ENCODER_FAULT"),
    (3, 0x80, "ENCODER_POSITION_INVALID"),
    (3, 0x10, "LOW_SUPPLY_VOLTAGE"),
    (3, 0x08, "INVALID_FIRMWARE"),
    (3, 0x02, "CAN_BUS_ERROR"),
    (3, 0x01, "POSITION_REPORT_NOT_RECEIVED"),
]


@pytest.mark.parametrize(("index", "bit", "name"), STATUS_C_D)
def test_hardware_status_bytes_c_and_d_by_name(index: int, bit: int, name: str) -> None:
    data = bytearray(4)
    data[index] = bit
    status = HardwareStatus.from_bytes(bytes(data))
    assert status == HardwareStatus[name]
    assert status.flag_names() == [name]
    assert status.to_bytes() == bytes(data)


def test_hardware_status_all_four_bytes_round_trip() -> None:
    every = HardwareStatus.NONE
    for flag in HardwareStatus:
        every |= flag
    data = every.to_bytes()
    assert data == bytes([0xFF, 0xFF, 0x1E, 0x9B])
    assert HardwareStatus.from_bytes(data) == every
    assert len(every.flag_names()) == 25
    # Reserved bits are kept, never dropped, and never named.
    reserved = HardwareStatus.from_bytes(bytes([0, 0, 0xE1, 0x64]))
    assert reserved.flag_names() == []
    assert reserved.to_bytes() == bytes([0, 0, 0xE1, 0x64])
    mixed = HardwareStatus.from_bytes(bytes([0x40, 0x04, 0x10, 0x10]))
    assert mixed.flag_names() == [
        "OVER_HUMIDITY",
        "OVER_PRESSURE",
        "JAW_ZERO_REQUIRED",
        "LOW_SUPPLY_VOLTAGE",
    ]


def test_packet_value_semantics() -> None:
    a = Packet(DeviceID.B, PacketID.POSITION, b"\x00\x00\x00\x40")
    b = Packet(2, 3, bytearray(b"\x00\x00\x00\x40"))  # type: ignore[arg-type]
    assert a == b and hash(a) == hash(b)
    assert type(b.data) is bytes
    assert b.device_id is DeviceID.B
    assert a.key == (2, 3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.data = b""  # type: ignore[misc]
    assert repr(a) == "Packet(DeviceID.B, PacketID.POSITION, b'\\x00\\x00\\x00@')"
    assert repr(Packet(0x42, 0x77)) == "Packet(0x42, 0x77, b'')"
    assert Packet(1, 3, b"\x01\x02").u8s() == [1, 2]
    assert decode_packet(a.encode()) == a


def test_integer_like_ids_are_accepted() -> None:
    class Index:
        def __index__(self) -> int:
            return 5

    packet = Packet(Index(), Index())  # type: ignore[arg-type]
    assert (packet.device_id, packet.packet_id) == (DeviceID.E, PacketID.CURRENT)
    assert encode_packet(Index(), 3, b"") == Packet(5, 3).encode()  # type: ignore[arg-type]


def test_end_effector_builders() -> None:
    pos = commands.end_position(DeviceID.E, 100.0, -20.0, 250.0, 0.5, 0.0, -1.0)
    assert pos.key == (DeviceID.E, PacketID.KM_END_POS)
    assert pos.floats() == pytest.approx([100.0, -20.0, 250.0, 0.5, 0.0, -1.0])
    assert len(pos.data) == 24
    vel = commands.end_velocity(DeviceID.E, 0.0, 0.0, 20.0)
    assert vel.key == (DeviceID.E, PacketID.KM_END_VEL)
    assert vel.floats() == [0.0, 0.0, 20.0, 0.0, 0.0, 0.0]
    with pytest.raises(PayloadError, match="z must be finite"):
        commands.end_position(DeviceID.E, 0.0, 0.0, math.inf, 0.0, 0.0, 0.0)
    with pytest.raises(PayloadError, match="wz must be finite"):
        commands.end_velocity(DeviceID.E, 0.0, 0.0, 0.0, wz=math.nan)
