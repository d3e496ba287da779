"""Builders for the packets a host sends. Each validates its arguments, so a bad command is
refused here with a clear message instead of being ignored (or misread) by the arm."""

from __future__ import annotations

from collections.abc import Iterable

from .errors import PayloadError
from .ids import LIMIT_PACKETS, Mode, PacketID
from .packet import Packet
from .payload import checked_ids, finite, pack_floats

MAX_REQUEST_IDS = 10
HEARTBEAT_SLOTS = 10


def position(device_id: int, rad: float) -> Packet:
    """Absolute position (rad; mm for the jaws). The arm ignores out-of-limit targets."""
    return Packet(device_id, PacketID.POSITION, pack_floats(finite("position", rad)))


def velocity(device_id: int, value: float) -> Packet:
    """Velocity (rad/s; mm/s for the jaws); the arm saturates it at its limit."""
    return Packet(device_id, PacketID.VELOCITY, pack_floats(finite("velocity", value)))


def current(device_id: int, milliamps: float) -> Packet:
    """Motor current in mA; the arm saturates it at its limit."""
    return Packet(device_id, PacketID.CURRENT, pack_floats(finite("current", milliamps)))


def mode(device_id: int, value: Mode | int) -> Packet:
    """MODE with its one-byte payload (never b'', which `bytes(Mode.STANDBY)` would give)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise PayloadError(f"mode must be a Mode (or an int 0..255), got {value!r}")
    return Packet(device_id, PacketID.MODE, bytes((int(value),)))


def request(device_id: int, packet_ids: Iterable[int]) -> Packet:
    """REQUEST: 1 to 10 packet ids; the device answers one packet per id."""
    ids = checked_ids("request", packet_ids, 1, MAX_REQUEST_IDS)
    return Packet(device_id, PacketID.REQUEST, bytes(ids))


def heartbeat_set(device_id: int, packet_ids: Iterable[int]) -> Packet:
    """HEARTBEAT_SET: up to 10 ids sent periodically, zero-padded to 10 (none clears it)."""
    ids = checked_ids("heartbeat_set", packet_ids, 0, HEARTBEAT_SLOTS)
    return Packet(device_id, PacketID.HEARTBEAT_SET, bytes(ids) + bytes(HEARTBEAT_SLOTS - len(ids)))


def heartbeat_frequency(device_id: int, hz: int) -> Packet:
    """HEARTBEAT_FREQUENCY in whole Hz, 0..255; 0 turns the heartbeat off (saved on the arm)."""
    if isinstance(hz, bool) or not isinstance(hz, int) or not 0 <= hz <= 0xFF:
        raise PayloadError(f"heartbeat frequency must be an int 0..255 Hz, got {hz!r}")
    return Packet(device_id, PacketID.HEARTBEAT_FREQUENCY, bytes((hz,)))


def limits(device_id: int, packet_id: PacketID | int, maximum: float, minimum: float) -> Packet:
    """POSITION/VELOCITY/CURRENT_LIMITS, payload [max, min] (protocol 1.12 order).

    `maximum < minimum` is refused: it is what the older [min, max] order looks like.
    """
    if packet_id not in LIMIT_PACKETS:
        raise PayloadError(
            f"limits takes POSITION_LIMITS, VELOCITY_LIMITS or CURRENT_LIMITS, got {packet_id!r}"
        )
    hi = finite("maximum", maximum)
    lo = finite("minimum", minimum)
    if hi < lo:
        raise PayloadError(f"limit maximum {hi} is below minimum {lo} (order is max, min)")
    return Packet(device_id, packet_id, pack_floats(hi, lo))


def save(device_id: int) -> Packet:
    """SAVE (payload 0x00): store settings on one device; send it to each device."""
    return Packet(device_id, PacketID.SAVE, b"\x00")


def end_position(
    device_id: int, x_mm: float, y_mm: float, z_mm: float, roll: float, pitch: float, yaw: float
) -> Packet:
    """KM_END_POS: move the tool centre point to (x, y, z) mm and three angles (rad, R =
    Rz(yaw) Ry(pitch) Rx(roll)). Send it to the base device (0x05 on the Alpha 5); a 4-joint
    arm follows the position and the roll about the tool axis only (docs/protocol.md)."""
    values = (x_mm, y_mm, z_mm, roll, pitch, yaw)
    names = ("x", "y", "z", "roll", "pitch", "yaw")
    return Packet(
        device_id,
        PacketID.KM_END_POS,
        pack_floats(*(finite(n, v) for n, v in zip(names, values, strict=True))),
    )


def end_velocity(
    device_id: int,
    vx_mm_s: float,
    vy_mm_s: float,
    vz_mm_s: float,
    wx: float = 0.0,
    wy: float = 0.0,
    wz: float = 0.0,
) -> Packet:
    """KM_END_VEL: Cartesian velocity of the tool centre point, mm/s and rad/s in the base
    frame, to the base device; all zeros stops. A joint command ends it."""
    values = (vx_mm_s, vy_mm_s, vz_mm_s, wx, wy, wz)
    names = ("vx", "vy", "vz", "wx", "wy", "wz")
    return Packet(
        device_id,
        PacketID.KM_END_VEL,
        pack_floats(*(finite(n, v) for n, v in zip(names, values, strict=True))),
    )


#: FORCE_TORQUE (0xD8) carries six float32: force x, y, z (N), then torque x, y, z (N m),
#: in the sensor's frame (z along the sensor's axis). Sent to the device that reports it
#: with all six zero, it tares the sensor (docs/protocol.md, "Force-torque").
FORCE_TORQUE_VALUES = 6


def force_torque_tare(device_id: int) -> Packet:
    """FORCE_TORQUE of six zeros: the sensor takes its present reading as zero. Send it to
    the device that reports the sensor (the Bravo's router, 0x0D)."""
    return Packet(device_id, PacketID.FORCE_TORQUE, pack_floats(*(0.0,) * FORCE_TORQUE_VALUES))
