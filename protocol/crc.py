"""CRC-8 of BPL frames: width 8, poly 0x4D, reflected in and out, init 0x00, xorout 0xFF.

Table-driven, one lookup per byte: the bit-serial loop public implementations use costs eight
Python iterations per byte, and every received byte goes through this.
"""

from __future__ import annotations

POLY = 0x4D
_POLY_REFLECTED = 0xB2  # 0x4D with its 8 bits reversed, for the LSB-first register
XOR_OUT = 0xFF


def _make_table() -> bytes:
    table = bytearray(256)
    for i in range(256):
        reg = i
        for _ in range(8):
            reg = (reg >> 1) ^ _POLY_REFLECTED if reg & 1 else reg >> 1
        table[i] = reg
    return bytes(table)


TABLE: bytes = _make_table()

# Register value after running a message *and* its own CRC byte through the table: a frame
# is intact iff its whole raw form leaves this residue, so the check needs one pass.
RESIDUE: int = TABLE[XOR_OUT]


def crc8(data: bytes | bytearray | memoryview) -> int:
    """CRC-8 of `data` as carried in the frame's last byte."""
    reg = 0
    table = TABLE
    for byte in data:
        reg = table[reg ^ byte]
    return reg ^ XOR_OUT
