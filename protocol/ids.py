"""Ids and flags of the BPL protocol (version 1) as listed in the project's fact sheet.

Unknown ids are legal on the wire: the codec hands them out as plain ints, so nothing here may
be used to reject a frame.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag
from typing import Literal, SupportsIndex

from .errors import PayloadError


class PacketID(IntEnum):
    MODE = 0x01
    VELOCITY = 0x02
    POSITION = 0x03
    CURRENT = 0x05
    INDEXED_POSITION = 0x0D
    RELATIVE_POSITION = 0x0E
    POSITION_LIMITS = 0x10
    VELOCITY_LIMITS = 0x11
    CURRENT_LIMITS = 0x12
    FACTORY_CLIMATE = 0x28  # 3 x f32 [temperature degC, pressure bar, humidity %] at assembly
    SAVE = 0x50
    # Presets, obstacles and collision ids are listed by range only: named by their hex id.
    PRESET_55 = 0x55
    PRESET_56 = 0x56
    PRESET_57 = 0x57
    PRESET_58 = 0x58
    PRESET_59 = 0x59
    PRESET_5A = 0x5A
    PRESET_5B = 0x5B
    PRESET_5C = 0x5C
    PRESET_5D = 0x5D
    PRESET_5E = 0x5E
    REQUEST = 0x60
    SERIAL_NUMBER = 0x61
    MODEL_NUMBER = 0x62
    DEVICE_ID = 0x64
    HUMIDITY = 0x65
    INTERNAL_HUMIDITY = 0x65  # the "Monitor" section's name (V1.12.1)
    TEMPERATURE = 0x66
    INTERNAL_TEMPERATURE = 0x66
    INTERNAL_PRESSURE = 0x67
    DEVICE_TYPE = 0x67  # newer SDKs reuse 0x67 and move pressure to 0x6E
    HARDWARE_STATUS = 0x68
    SOFTWARE_VERSION = 0x6C
    PRESSURE = 0x6E
    VOLTAGE = 0x90
    HEARTBEAT_SET = 0x91
    HEARTBEAT_FREQUENCY = 0x92
    VOLTAGE_THRESHOLD = 0x99
    KM_END_POS = 0xA1
    KM_END_VEL = 0xA2
    OBSTACLE_A5 = 0xA5
    OBSTACLE_A6 = 0xA6
    OBSTACLE_A7 = 0xA7
    OBSTACLE_A8 = 0xA8
    OBSTACLE_A9 = 0xA9
    OBSTACLE_AA = 0xAA
    OBSTACLE_AB = 0xAB
    OBSTACLE_AC = 0xAC
    OBSTACLE_AD = 0xAD
    OBSTACLE_AE = 0xAE
    COLLISION_AF = 0xAF
    COLLISION_B1 = 0xB1
    FORCE_TORQUE = 0xD8  # 6 x f32 [Fx Fy Fz N, Tx Ty Tz N m]; the vendor's ATI_FT
    RESET = 0xFD
    BOOTLOADER = 0xFF


LIMIT_PACKETS = frozenset(
    {PacketID.POSITION_LIMITS, PacketID.VELOCITY_LIMITS, PacketID.CURRENT_LIMITS}
)


class DeviceID(IntEnum):
    """Alpha 5 joints by letter (A jaws .. E base), with descriptive aliases, plus Bravo ids."""

    A = 0x01
    B = 0x02
    C = 0x03
    D = 0x04
    E = 0x05
    F = 0x06  # Bravo only
    G = 0x07  # Bravo only
    ROUTER = 0x0D  # Bravo Ethernet router
    COMPUTE = 0x0E  # Bravo compute module
    BROADCAST = 0xFF
    JAWS = 0x01
    WRIST_ROTATE = 0x02
    ELBOW = 0x03
    SHOULDER = 0x04
    BASE_ROTATE = 0x05


class Mode(IntEnum):
    """Control modes (the MODE packet's u8). Others exist; unknown values decode as ints."""

    STANDBY = 0x00
    DISABLE = 0x01
    POSITION = 0x02
    VELOCITY = 0x03
    CURRENT = 0x04
    ZERO_VELOCITY = 0x15
    POSITION_HOLD = 0x1D
    PASSIVE = 0x26

    def payload(self) -> bytes:
        """The one-byte MODE payload (`bytes(Mode.STANDBY)` would be b'', a known defect)."""
        return bytes((self.value,))


#: Mode values a widely used open C++ client library defines that protocol V1.12.1 does not
#: document (their meaning is not public). The virtual arm ignores and counts them.
UNDOCUMENTED_MODES: frozenset[int] = frozenset({0x13, 0x14, 0x17, 0x18, 0x1A, 0x1C})

_STATUS_SIZE = 4


class HardwareStatus(IntFlag):
    """HARDWARE_STATUS flags; the value is the 4 status bytes read big-endian.

    The fact sheet names byte A "the high byte of the first u16" and lists it first; we take
    wire order A, B, C, D, so byte A (data[0]) holds bits 24..31, byte B (data[1]) bits
    16..23, byte C bits 8..15 and byte D bits 0..7. Reserved bits have no name; they are kept
    in the value, never dropped. Some flags only exist on some products (docs/protocol.md,
    section 8).
    """

    NONE = 0
    # byte A
    FLASH_READ_FAILED = 0x80 << 24
    OVER_HUMIDITY = 0x40 << 24
    OVER_TEMPERATURE = 0x20 << 24
    SERIAL_ERROR = 0x10 << 24
    CRC_ERROR = 0x08 << 24
    MOTOR_DRIVER_FAULT = 0x04 << 24
    ENCODER_POSITION_ERROR = 0x02 << 24
    ENCODER_NOT_DETECTED = 0x01 << 24
    # byte B
    AXIS_CONFLICT = 0x80 << 16
    MOTOR_NOT_CONNECTED = 0x40 << 16
    MOTOR_OVER_CURRENT = 0x20 << 16
    INNER_ENCODER_ERROR = 0x10 << 16
    DEVICE_ID_CONFLICT = 0x08 << 16
    OVER_PRESSURE = 0x04 << 16
    DRIVER_OVER_CURRENT_UNDER_VOLTAGE = 0x02 << 16
    DRIVER_OVER_TEMPERATURE = 0x01 << 16
    # byte C
    JAW_ZERO_REQUIRED = 0x10 << 8
    JOINT_SERVICE_DUE = 0x08 << 8  # Bravo
    READ_PROTECTION_ENABLED = 0x04 << 8
    ENCODER_FAULT = 0x02 << 8  # from backlash
    # byte D
    ENCODER_POSITION_INVALID = 0x80  # factory calibration
    LOW_SUPPLY_VOLTAGE = 0x10
    INVALID_FIRMWARE = 0x08  # Bravo compute module
    CAN_BUS_ERROR = 0x02
    POSITION_REPORT_NOT_RECEIVED = 0x01  # compute module

    @classmethod
    def from_bytes(  # type: ignore[override]
        cls,
        data: bytes | bytearray | memoryview,
        byteorder: Literal["little", "big"] = "big",
        *,
        signed: bool = False,
    ) -> HardwareStatus:
        """Flags from a HARDWARE_STATUS payload; exactly 4 bytes, else `PayloadError`."""
        if len(data) != _STATUS_SIZE:
            raise PayloadError(
                f"HARDWARE_STATUS payload must be {_STATUS_SIZE} bytes, got {len(data)}"
            )
        if byteorder != "big" or signed:
            raise PayloadError("HARDWARE_STATUS bytes are unsigned and read in wire order (big)")
        return cls(int.from_bytes(data, "big"))

    def to_bytes(  # type: ignore[override]
        self,
        length: SupportsIndex = _STATUS_SIZE,
        byteorder: Literal["little", "big"] = "big",
        *,
        signed: bool = False,
    ) -> bytes:
        """The 4-byte HARDWARE_STATUS payload for these flags."""
        if int(length) != _STATUS_SIZE or byteorder != "big" or signed:
            raise PayloadError("HARDWARE_STATUS is 4 unsigned bytes in wire order (big)")
        return int(self).to_bytes(_STATUS_SIZE, "big")

    def flag_names(self) -> list[str]:
        """Names of the documented flags that are set (undocumented bits are not named)."""
        return [flag.name for flag in type(self) if flag.value and flag in self and flag.name]
