"""companion.io.mavlink_fast against pymavlink on real bytes: every message the lean decoder gives
must equal pymavlink's own decode of the same frame (type, fields and their Python types, frame
bytes, header, CRC, signed flag), and a datagram stream through DatagramParser must give the very
messages pymavlink's stream parser gives, in order -- v1 and v2 frames, truncated v2 payloads,
signed frames, garbage, bad CRCs, unknown ids and frames split across datagrams."""
from __future__ import annotations

import random
import zlib

import pytest

import companion.io.mavlink as M
from companion.io import mavlink_codec
from companion.io.mavlink_fast import FAST_MESSAGES, DatagramParser, FastFrameDecoder, layouts
from companion.io.mavlink_signing import sign_encoder

mav = mavlink_codec.mavlink2


def encoder(seq=0, sysid=1, compid=1):
    enc = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    enc.seq = seq & 0xFF
    return enc


def reference_parser():
    p = mav.MAVLink(None)
    p.robust_parsing = True
    return p


def snapshot(msg) -> tuple:
    """Everything a consumer of a message can see."""
    h = msg.get_header()
    fields = {k: (type(v).__name__, v) for k, v in msg.to_dict().items()}
    return (msg.get_type(), fields, bytes(msg.get_msgbuf()), bytes(msg.get_payload() or b""), msg.get_crc(),
            msg.get_signed(), (h.msgId, h.incompat_flags, h.compat_flags, h.mlen, h.seq, h.srcSystem,
                               h.srcComponent))


def random_message(name: str, rng: random.Random, zero_tail: bool = False):
    """A message of type ``name`` with random field values in range (the last wire fields zero when
    ``zero_tail``: pymavlink's MAVLink 2 packing then truncates the payload)."""
    cls = next(c for c in mav.mavlink_map.values() if c.msgname == name)
    ints = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
            "uint32_t": (0, 2 ** 32 - 1), "int32_t": (-2 ** 31, 2 ** 31 - 1), "uint64_t": (0, 2 ** 64 - 1),
            "int64_t": (-2 ** 63, 2 ** 63 - 1)}
    args = []
    for fname, ftype, alen in zip(cls.fieldnames, cls.fieldtypes, cls.array_lengths):
        def one():
            if ftype in ("float", "double"):
                return rng.uniform(-1e3, 1e3)
            lo, hi = ints[ftype]
            return rng.randint(lo, hi)
        args.append([one() for _ in range(alen)] if alen else one())
    msg = cls(*args)
    if zero_tail:        # zero the wire-order tail (largest fields come first on the wire)
        for fname in cls.ordered_fieldnames[len(cls.ordered_fieldnames) // 2:]:
            v = getattr(msg, fname)
            setattr(msg, fname, [0] * len(v) if isinstance(v, list) else type(v)(0))
    return msg


def test_layouts_cover_the_fast_messages():
    lay = layouts()
    assert sorted(x.cls.msgname for x in lay.values()) == sorted(FAST_MESSAGES)
    with pytest.raises(ValueError):
        layouts(("HIGHRES_IMU", "NO_SUCH_MESSAGE"))


@pytest.mark.parametrize("name", FAST_MESSAGES)
@pytest.mark.parametrize("variant", ["v2", "v2-truncated", "v1", "v2-signed"])
def test_each_fast_message_equals_pymavlink(name, variant):
    rng = random.Random(zlib.crc32(f"{name} {variant}".encode()))
    for k in range(20):
        enc = encoder(seq=k * 7, sysid=1 + k % 3, compid=1 + k % 2)
        if variant == "v2-signed":
            sign_encoder(enc, bytes(range(32)), link_id=3, timestamp=1_000_000 + k)
        msg = random_message(name, rng, zero_tail=(variant == "v2-truncated"))
        frame = bytes(msg.pack(enc, force_mavlink1=(variant == "v1")))
        assert frame[0] == (0xFE if variant == "v1" else 0xFD)
        if variant == "v2-truncated":
            assert frame[1] < layouts()[msg.get_msgId()].size      # the sender really cut the payload
        if variant == "v2-signed":
            assert frame[2] & 0x01
        want = reference_parser().parse_buffer(frame)
        assert len(want) == 1 and want[0].get_type() == name
        got, rest = FastFrameDecoder().decode(frame)
        assert rest == b"" and len(got) == 1
        assert snapshot(got[0]) == snapshot(want[0])
        # the field log records get_msgbuf(); replay parses it with pymavlink: same message again
        again = reference_parser().parse_buffer(bytes(got[0].get_msgbuf()))
        assert snapshot(again[0]) == snapshot(want[0])


def test_the_decoder_stops_where_it_must():
    rng = random.Random(5)
    imu = bytes(random_message("HIGHRES_IMU", rng).pack(encoder()))
    hb = bytes(mav.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(encoder()))
    bad_crc = bytearray(imu)
    bad_crc[-1] ^= 0xFF
    bad_flags = bytearray(imu)
    bad_flags[2] = 0x02                      # an incompat flag nobody knows
    dec = FastFrameDecoder()
    for data, n_taken in [(imu + imu, 2), (imu + hb + imu, 1), (hb + imu, 0), (b"\x00garbage" + imu, 0),
                          (imu + imu[:20], 1), (bytes(bad_crc) + imu, 0), (bytes(bad_flags), 0), (imu[:9], 0)]:
        got, rest = dec.decode(data)
        assert len(got) == n_taken
        assert rest == data[sum(len(bytes(m.get_msgbuf())) for m in got):]


def frame_soup(rng: random.Random, n: int) -> list[bytes]:
    """A MAVLink byte stream of high-rate and other messages, v1/v2, some truncated payloads and
    signed frames, with garbage, corrupted CRCs and unknown ids between them."""
    out = []
    for k in range(n):
        r = rng.random()
        enc = encoder(seq=k, sysid=1 if rng.random() < 0.9 else 42)
        if r < 0.05:
            out.append(bytes(rng.randrange(256) for _ in range(rng.randint(1, 30))))
            continue
        if r < 0.12:
            msg = mav.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3)
        elif r < 0.16:
            msg = mav.MAVLink_statustext_message(6, b"hello", 0, 0)
        else:
            msg = random_message(rng.choice(FAST_MESSAGES), rng, zero_tail=rng.random() < 0.3)
        if rng.random() < 0.1:
            sign_encoder(enc, bytes(32 * [7]), timestamp=10_000 + k)
        frame = bytearray(msg.pack(enc, force_mavlink1=rng.random() < 0.1 and msg.get_msgId() < 256))
        if rng.random() < 0.04:
            frame[-1] ^= 0x5A                    # bad CRC
        elif rng.random() < 0.03 and frame[0] == 0xFD:
            frame[7] = 0xEE                      # an id outside the dialect
            frame[8] = 0xEE
        out.append(bytes(frame))
    return out


@pytest.mark.parametrize("seed", range(6))
def test_datagram_stream_equals_pymavlink_stream(seed):
    """Datagrams of one to three frames, some cut in two (frames split across datagrams): the
    parser gives exactly pymavlink's messages (BAD_DATA and UNKNOWN included), in order."""
    rng = random.Random(seed)
    frames = frame_soup(rng, 400)
    cuts, carry, k = [], b"", 0
    while k < len(frames):        # 1-3 frames a datagram; now and then one cut in two
        n = rng.randint(1, 3)
        d = carry + b"".join(frames[k:k + n])
        k += n
        carry = b""
        if rng.random() < 0.15 and len(d) > 2:
            j = rng.randrange(1, len(d))
            d, carry = d[:j], d[j:]
        cuts.append(d)
    if carry:
        cuts.append(carry)
    ref = reference_parser()
    want = []
    for d in cuts:
        want += ref.parse_buffer(d) or []
    mine = mav.MAVLink(None)
    mine.robust_parsing = True
    posted = []
    parser = DatagramParser(mine, post=posted.append)
    got = []
    for d in cuts:
        got += parser.feed(d)
    assert [snapshot(m) if m.get_type() not in ("BAD_DATA",) else ("BAD", bytes(m.get_msgbuf())) for m in got] == \
           [snapshot(m) if m.get_type() not in ("BAD_DATA",) else ("BAD", bytes(m.get_msgbuf())) for m in want]
    assert parser.fast.counters["frames"] > 0 and len(posted) > 0       # both paths were exercised
    assert len(posted) + parser.fast.counters["frames"] == len(got)
    assert mine.total_bytes_received == ref.total_bytes_received
    assert mine.total_packets_received == ref.total_packets_received


def test_whole_frames_one_per_datagram_all_take_the_fast_path():
    rng = random.Random(11)
    frames = [bytes(random_message(rng.choice(FAST_MESSAGES), rng).pack(encoder(seq=k))) for k in range(200)]
    parser = DatagramParser(reference_parser())
    got = [m for f in frames for m in parser.feed(f)]
    assert parser.fast.counters == {"frames": 200, "handed_over": 0}
    assert [snapshot(m) for m in got] == [snapshot(reference_parser().parse_buffer(f)[0]) for f in frames]


# ------------------------------------------------------------------ the link's receive path
def _free_port() -> int:
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_link_delivers_the_datagrams_messages_to_its_sink_and_raises_what_the_sink_raises():
    """Over a real udpin socket on 127.0.0.1: every frame the 'autopilot' sends reaches the sink as
    the message pymavlink makes of it, raw bytes = the frame (what the field log records); a sink
    that raises ends deliver_to with that exception."""
    import asyncio
    import socket

    rng = random.Random(3)
    frames = [bytes(random_message(rng.choice(FAST_MESSAGES), rng).pack(encoder(seq=k))) for k in range(50)]
    frames.insert(10, bytes(mav.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3).pack(encoder(seq=99))))
    frames.insert(20, frames[19][:15])                       # a cut frame: pymavlink holds it

    async def main():
        port = _free_port()
        link = M.MavlinkLink(f"udpin:127.0.0.1:{port}")
        await link.start()
        assert link._fast is not None
        got = []
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

        def sink(lm):
            got.append(lm)
            if lm.msg.get_type() == "HEARTBEAT" and len(got) > 40:
                raise RuntimeError("sink failed")

        task = asyncio.create_task(link.deliver_to(sink))
        for f in frames:
            tx.sendto(f, ("127.0.0.1", port))
            await asyncio.sleep(0.002)
        await asyncio.sleep(0.2)
        assert not task.done()
        tx.sendto(frames[10], ("127.0.0.1", port))           # a heartbeat: the sink raises
        with pytest.raises(RuntimeError, match="sink failed"):
            await asyncio.wait_for(task, 2.0)
        tx.close()
        await link.close()
        return got

    got = asyncio.run(main())
    ref = reference_parser()
    want = [m for f in frames + [frames[10]] for m in (ref.parse_buffer(f) or [])]
    want = [m for m in want if m.get_type() not in ("BAD_DATA",) and not m.get_type().startswith("UNKNOWN")]
    assert [snapshot(lm.msg) for lm in got] == [snapshot(m) for m in want]
    assert all(lm.raw == bytes(lm.msg.get_msgbuf()) for lm in got)


def test_link_without_a_sink_still_queues_and_ends_deliver_to_on_close():
    import asyncio
    import socket

    frame = bytes(random_message("HIGHRES_IMU", random.Random(1)).pack(encoder()))

    async def main():
        port = _free_port()
        link = M.MavlinkLink(f"udpin:127.0.0.1:{port}")
        await link.start()
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.sendto(frame, ("127.0.0.1", port))
        lm = await link.recv(2.0)
        assert lm is not None and lm.raw == frame
        task = asyncio.create_task(link.deliver_to(lambda lm: None))
        await asyncio.sleep(0.05)
        await link.close()
        await asyncio.wait_for(task, 2.0)                    # returns (no exception) on close
        tx.close()

    asyncio.run(main())
