"""CRC-24Q (RTCM 10403 / Qualcomm: polynomial 0x1864CFB, init 0, no reflection, no final xor).

The RTCM framer computes one CRC per candidate frame, and a hostile stream can make a candidate of
every few bytes, so the CRC runs at C speed: ``anycrc`` (crcany by Mark Adler, abi3 wheels, about
1 us per kB here; its ``CRC24-LTE-A`` model is CRC-24Q exactly) when installed, else a table-driven
pure-Python fallback (about 150 us per kB) so the package still imports without it.
``BACKEND`` says which one runs.
"""
from __future__ import annotations

_POLY = 0x1864CFB


def _table() -> list[int]:
    table = []
    for i in range(256):
        c = i << 16
        for _ in range(8):
            c <<= 1
            if c & 0x1000000:
                c ^= _POLY
        table.append(c & 0xFFFFFF)
    return table


_TABLE = _table()


def crc24q_python(data: bytes | bytearray | memoryview) -> int:
    crc = 0
    table = _TABLE
    for b in data:
        crc = ((crc << 8) & 0xFFFFFF) ^ table[((crc >> 16) ^ b) & 0xFF]
    return crc


try:
    import anycrc as _anycrc

    _model = _anycrc.Model("CRC24-LTE-A")
    if _model.calc(b"123456789") != 0xCDE703:        # the catalogue check value of CRC-24/LTE-A
        raise ImportError("anycrc CRC24-LTE-A is not CRC-24Q")
    crc24q = _model.calc
    BACKEND = "anycrc"
except Exception:                                      # not installed, or not what we expect
    crc24q = crc24q_python
    BACKEND = "python"

__all__ = ["crc24q", "crc24q_python", "BACKEND"]
