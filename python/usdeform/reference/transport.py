"""Plain-Python twin of the OpenIGTLink CRC-64."""

from __future__ import annotations

#: The CRC-64 polynomial of OpenIGTLink (ECMA-182), its x^64 term implied.
_ECMA_182 = 0x42F0E1EBA9EA3693


def _crc64_table() -> list[int]:
    """The CRC-64 of each byte value alone, shifted through the polynomial bit by bit."""
    table = []
    for byte in range(256):
        crc = byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ _ECMA_182) if crc >> 63 else crc << 1
            crc &= (1 << 64) - 1
        table.append(crc)
    return table


def crc64(data: bytes, crc: int = 0) -> int:
    """The OpenIGTLink CRC-64 of ``data`` continued from ``crc``: the ECMA-182 polynomial, bits not
    reflected, initial value 0, no final XOR, one table look-up a byte."""
    table = _crc64_table()
    for byte in data:
        crc = table[(crc >> 56) ^ byte] ^ ((crc << 8) & ((1 << 64) - 1))
    return crc
