"""A minimal PX4 ULog writer (file format version 1: header, flag bits, formats, subscriptions,
data), enough for pyulog to read the topics a test writes (test helper)."""
from __future__ import annotations

import struct
from pathlib import Path

_CODES = {"uint64_t": "Q", "int64_t": "q", "uint32_t": "I", "int32_t": "i", "uint16_t": "H", "int16_t": "h",
          "uint8_t": "B", "int8_t": "b", "float": "f", "double": "d", "bool": "?"}


class ULogWriter:
    def __init__(self, start_us: int = 0):
        self.start_us = start_us
        self.topics: dict[str, tuple[int, struct.Struct, str]] = {}   # name -> (msg id, packing, format text)
        self.rows: list[tuple[int, int, bytes]] = []                    # (timestamp, msg id, packed)

    def topic(self, name: str, fields: list[tuple[str, str]]) -> None:
        """``fields``: (type, name), 'float[3]' for an array; the first is 'uint64_t timestamp'."""
        codes = []
        for typ, _ in fields:
            base, _, n = typ.partition("[")
            codes.append((int(n[:-1]) if n else 1) * _CODES[base] if n else _CODES[base])
        text = f"{name}:" + "".join(f"{typ} {field};" for typ, field in fields)
        self.topics[name] = (len(self.topics), struct.Struct("<" + "".join(codes)), text)

    def write(self, name: str, timestamp_us: int, *values) -> None:
        msg_id, st, _ = self.topics[name]
        flat = []
        for v in (timestamp_us, *values):
            flat.extend(v if isinstance(v, (list, tuple, bytes)) else [v])
        self.rows.append((int(timestamp_us), msg_id, st.pack(*flat)))

    @staticmethod
    def _msg(kind: bytes, payload: bytes) -> bytes:
        return struct.pack("<HB", len(payload), kind[0]) + payload

    def save(self, path: Path) -> Path:
        out = bytearray(b"ULog\x01\x12\x35\x01" + struct.pack("<Q", self.start_us))
        out += self._msg(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
        for _, _, text in self.topics.values():
            out += self._msg(b"F", text.encode())
        for name, (msg_id, _, _) in self.topics.items():
            out += self._msg(b"A", struct.pack("<BH", 0, msg_id) + name.encode())
        for _, msg_id, packed in sorted(self.rows, key=lambda r: r[0]):
            out += self._msg(b"D", struct.pack("<H", msg_id) + packed)
        path.write_bytes(bytes(out))
        return path
