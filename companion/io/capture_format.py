"""What a binary capture holds: RTCM 3 or UBX frames, told by a checksummed frame near its start.

A capture rarely starts on a frame: ``str2str`` or a serial logger started mid-stream leaves the
tail of a frame first (the real Hiroshima base capture starts with 12 such bytes), so the first
byte says nothing.  A file is taken for a capture when one of its first :data:`SCAN_BYTES` starts
a frame whose checksum holds (CRC-24Q for RTCM, Fletcher-8 for UBX) and that is followed by the
next frame's sync or by the end of the file: a text file (RINEX) has neither, and two checks of 24
and 16 bits make a chance match in a compressed file negligible.
"""
from __future__ import annotations

from .crc24q import crc24q
from .ubx import ubx_checksum

SCAN_BYTES = 8192
_RTCM_PREAMBLE = 0xD3
_UBX_SYNC = b"\xb5\x62"


def _head(path, n: int) -> bytes:
    with open(path, "rb") as fh:
        return fh.read(n)


def _rtcm_frame_end(buf: bytes, i: int) -> int | None:
    """End of a checksummed RTCM 3 frame starting at ``buf[i]``, or None."""
    if i + 6 > len(buf) or buf[i] != _RTCM_PREAMBLE or buf[i + 1] & 0xFC:
        return None
    length = ((buf[i + 1] & 0x03) << 8) | buf[i + 2]
    end = i + 3 + length + 3
    if end > len(buf) or crc24q(buf[i:end - 3]) != int.from_bytes(buf[end - 3:end], "big"):
        return None
    return end


def _ubx_frame_end(buf: bytes, i: int) -> int | None:
    """End of a checksummed UBX frame starting at ``buf[i]``, or None."""
    if i + 8 > len(buf) or buf[i:i + 2] != _UBX_SYNC:
        return None
    length = int.from_bytes(buf[i + 4:i + 6], "little")
    end = i + 6 + length + 2
    if end > len(buf) or bytes(ubx_checksum(buf[i + 2:end - 2])) != buf[end - 2:end]:
        return None
    return end


def _holds(path, frame_end, sync: bytes) -> bool:
    buf = _head(path, SCAN_BYTES + 2048)
    return _holds_bytes(buf, len(buf) < SCAN_BYTES + 2048, frame_end, sync)   # whole: the file ends within it


def _holds_bytes(buf: bytes, whole: bool, frame_end, sync: bytes) -> bool:
    i = buf.find(sync[:1])
    while 0 <= i < SCAN_BYTES:
        end = frame_end(buf, i)
        if end is not None and (buf[end:end + len(sync)] == sync or (whole and end == len(buf))):
            return True
        i = buf.find(sync[:1], i + 1)
    return False


def is_rtcm_capture(path) -> bool:
    """RTCM 3 frames (a checksummed frame within the first :data:`SCAN_BYTES`)."""
    return _holds(path, _rtcm_frame_end, bytes([_RTCM_PREAMBLE]))


def is_ubx_capture(path) -> bool:
    """UBX frames (a checksummed frame within the first :data:`SCAN_BYTES`)."""
    return _holds(path, _ubx_frame_end, _UBX_SYNC)


def stream_kind(buf: bytes) -> str:
    """'ubx' or 'rtcm' when the start of a byte stream holds such frames (as :func:`is_ubx_capture`
    and :func:`is_rtcm_capture` tell a file), else ''."""
    head = bytes(buf[:SCAN_BYTES + 2048])
    whole = len(buf) <= len(head)
    if _holds_bytes(head, whole, _ubx_frame_end, _UBX_SYNC):
        return "ubx"
    if _holds_bytes(head, whole, _rtcm_frame_end, bytes([_RTCM_PREAMBLE])):
        return "rtcm"
    return ""


def is_dataflash_log(path) -> bool:
    """An ArduPilot DataFlash log: it starts with a FMT record (0xA3 0x95, type 128)."""
    return _head(path, 3) == b"\xa3\x95\x80"


def is_receiver_capture(path) -> bool:
    """A u-blox's RXM-RAWX stream: a UBX capture, or a DataFlash log whose GRXH/GRXS records are
    one (:mod:`companion.io.dataflash_raw`)."""
    return is_ubx_capture(path) or is_dataflash_log(path)


__all__ = ["is_rtcm_capture", "is_ubx_capture", "is_dataflash_log", "is_receiver_capture", "stream_kind",
           "SCAN_BYTES"]
