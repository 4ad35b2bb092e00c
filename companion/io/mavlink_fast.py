"""A lean MAVLink frame decoder for the few high-rate messages of the autopilot link.

Why: in the live service pymavlink's receive path (``recv_msg`` -> ``parse_char`` ->
``__parse_char_legacy`` -> ``decode`` -> ``post_message``) costs several times the struct unpack
it boils down to, for every one of the ~270 datagrams a second (200 Hz IMU, SERIAL_CONTROL
replies, ATTITUDE, ...).  :class:`FastFrameDecoder` takes the *leading complete frames* of a
datagram whose id is in its table and hands everything else to pymavlink, unchanged:

* MAVLink 2 (0xFD) and MAVLink 1 (0xFE) frames; the CRC is checked with the message's
  ``CRC_EXTRA`` (the dialect's, as pymavlink does); a v2 payload shorter than the message (trailing
  zeros truncated by the sender) is zero-padded, a longer one (extensions we do not know) is cut;
* a signed v2 frame (incompat flag 0x01) is taken as pymavlink takes it with no key: the 13-byte
  signature is skipped, ``_signed`` False -- the link does not use this decoder when signing is
  configured (:mod:`companion.io.mavlink_signing` must see every frame);
* it stops at the first byte it does not take -- no magic, unknown incompat flags, an id outside
  its table, a frame cut by the datagram's end, a bad CRC -- and returns the rest for pymavlink,
  whose robust parser then reports it exactly as before (BAD_DATA, resync, buffering).  Order is
  kept: nothing after that byte is decoded here.

The messages are pymavlink's own classes built with the fields pymavlink's ``decode`` would give
(same order, same Python types, same ``get_msgbuf()`` bytes, header and CRC), so the pipeline, the
field log (which records ``get_msgbuf()``) and replay (which parses the logged frame with
pymavlink) see no difference; ``tests/test_mavlink_fast.py`` cross-checks that on real bytes.
"""
from __future__ import annotations

import struct

from pymavlink.dialects.v20 import ardupilotmega as _dialect

MAGIC_V2 = 0xFD
MAGIC_V1 = 0xFE
HEADER_LEN_V2 = 10
HEADER_LEN_V1 = 6
SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01

#: the autopilot's high-rate messages (everything else is rare enough for pymavlink)
FAST_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE",
                 "SYSTEM_TIME", "SERIAL_CONTROL", "GPS_RAW_INT", "TIMESYNC")

_CRC16 = struct.Struct("<H")


def _crc_function():
    """CRC-16/MCRF4XX of bytes (pymavlink's x25crc): fastcrc's when pymavlink uses it."""
    fast = getattr(_dialect, "mcrf4xx", None)
    if fast is not None:
        return lambda b: fast(b, 0xFFFF)
    return lambda b: _dialect.x25crc(b).crc


class _MessageLayout:
    """How pymavlink's ``decode`` turns one message's payload into constructor arguments."""
    __slots__ = ("cls", "crc_extra", "unpack", "size", "order", "slices", "has_bytes")

    def __init__(self, cls):
        self.cls = cls
        self.crc_extra = cls.crc_extra
        self.unpack = cls.unpacker.unpack
        self.size = cls.unpacker.size
        self.has_bytes = any(t == "char" for t in cls.fieldtypes)
        lengths = list(cls.lengths)
        if sum(lengths) == len(lengths):           # no arrays: a permutation of the wire order
            self.order = tuple(cls.orders)
            self.slices = None
        else:                                      # arrays: (start, length) of each field, in order
            self.order = None
            self.slices = tuple((sum(lengths[:o]), lengths[o]) for o in cls.orders)

    def arguments(self, t: tuple) -> list:
        if self.slices is None:
            args = [t[i] for i in self.order]
        else:
            args = []
            for tip, n in self.slices:
                f = t[tip]
                args.append(f if n == 1 or isinstance(f, bytes) else list(t[tip:tip + n]))
        if self.has_bytes:
            args = [a.rstrip(b"\x00") if isinstance(a, bytes) else a for a in args]
        return args


def layouts(names=FAST_MESSAGES) -> dict[int, _MessageLayout]:
    """{message id: layout} for the named messages of the ardupilotmega dialect."""
    out = {}
    for cls in _dialect.mavlink_map.values():
        if cls.msgname in names:
            out[cls.id] = _MessageLayout(cls)
    missing = set(names) - {lay.cls.msgname for lay in out.values()}
    if missing:
        raise ValueError(f"not in the dialect: {', '.join(sorted(missing))}")
    return out


class FastFrameDecoder:
    """Decodes the leading complete frames of a datagram with ids in ``names`` (see module doc).

    ``mav`` (the connection's pymavlink ``MAVLink`` object) gets the byte/packet counters and the
    signed-frame count pymavlink would have kept for the frames taken here.
    Counter ``frames`` (taken here) and ``handed_over`` (datagrams with a rest for pymavlink)."""

    def __init__(self, mav=None, names=FAST_MESSAGES):
        self.mav = mav
        self._layouts = layouts(names)
        self._crc = _crc_function()
        self.counters = {"frames": 0, "handed_over": 0}

    def decode(self, data: bytes) -> tuple[list, bytes]:
        """(messages, rest): the messages of the leading frames taken, and the bytes from the first
        one not taken (b"" when all were)."""
        out = []
        i = 0
        n = len(data)
        lay_of = self._layouts
        crc = self._crc
        while i < n:
            magic = data[i]
            if magic == MAGIC_V2:
                if n - i < HEADER_LEN_V2:
                    break
                mlen = data[i + 1]
                incompat = data[i + 2]
                if incompat & ~IFLAG_SIGNED:
                    break
                lay = lay_of.get(data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16))
                hlen = HEADER_LEN_V2
                sig = SIGNATURE_LEN if incompat & IFLAG_SIGNED else 0
            elif magic == MAGIC_V1:
                if n - i < HEADER_LEN_V1:
                    break
                mlen = data[i + 1]
                incompat = 0
                lay = lay_of.get(data[i + 5])
                hlen = HEADER_LEN_V1
                sig = 0
            else:
                break
            if lay is None:
                break
            end_payload = i + hlen + mlen
            end = end_payload + 2 + sig
            if end > n:
                break
            frame = data[i:end]
            if crc(frame[1:hlen + mlen] + bytes((lay.crc_extra,))) != _CRC16.unpack_from(data, end_payload)[0]:
                break
            payload = frame[hlen:hlen + mlen]
            if mlen < lay.size:
                payload += bytes(lay.size - mlen)
            elif mlen > lay.size:
                payload = payload[:lay.size]
            msg = lay.cls(*lay.arguments(lay.unpack(payload)))
            msgbuf = bytearray(frame)
            msg._signed = False
            msg._msgbuf = msgbuf
            msg._payload = msgbuf[6:-(2 + sig)]            # sic: pymavlink's decode uses 6 for v2 too
            msg._crc = _CRC16.unpack_from(data, end_payload)[0]
            if magic == MAGIC_V2:
                msg._header = _dialect.MAVLink_header(lay.cls.id, incompat, data[i + 3], mlen, data[i + 4],
                                                      data[i + 5], data[i + 6])
            else:
                msg._header = _dialect.MAVLink_header(lay.cls.id, 0, 0, mlen, data[i + 2], data[i + 3], data[i + 4])
            out.append(msg)
            i = end
            if self.mav is not None:
                self.mav.total_packets_received += 1
                if sig:
                    self.mav.signing.sig_count += 1
        if self.mav is not None:
            self.mav.total_bytes_received += i
        self.counters["frames"] += len(out)
        if i < n:
            self.counters["handed_over"] += 1
            return out, data[i:]
        return out, b""


class DatagramParser:
    """One datagram at a time, the messages pymavlink's stream parser would give, in order: the
    lean decoder takes the datagram's leading high-rate frames when pymavlink holds nothing (no
    partial frame of an earlier datagram), pymavlink's parser (``mav``, robust parsing) everything
    from the first byte not taken, until it has no complete frame left.  ``post(msg)`` (the
    connection's ``post_message``, its per-message bookkeeping) is called for pymavlink's
    messages; ``on_error(exc)`` for an exception of pymavlink's parser (the rest of that call's
    input is lost, as with ``recv_msg``)."""

    def __init__(self, mav, post=None, on_error=None, names=FAST_MESSAGES):
        self.mav = mav
        self.fast = FastFrameDecoder(mav, names)
        self._post = post
        self._on_error = on_error

    def feed(self, data: bytes) -> list:
        mav = self.mav
        out = []
        if mav.buf_len() == 0:
            out, data = self.fast.decode(data)
            if not data:
                return out          # all taken (the common datagram): pymavlink has nothing to parse
        while True:
            try:
                msg = mav.parse_char(data)
            except Exception as exc:  # pymavlink raises on some malformed input
                if self._on_error is not None:
                    self._on_error(exc)
                data = b""
                continue
            data = b""
            if msg is None:
                return out
            if self._post is not None:
                self._post(msg)
            out.append(msg)


__all__ = ["FAST_MESSAGES", "DatagramParser", "FastFrameDecoder", "layouts"]
