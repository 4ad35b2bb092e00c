"""MAVLink 2 signing on the companion's link (companion.io.mavlink_signing), on real loopback UDP
sockets, against a peer that is pymavlink's own mavutil connection with pymavlink's own
``setup_signing``: what it signs we accept, what we send it verifies, and forged, wrongly signed or
replayed frames from the very same socket are dropped, counted and never reach the consumer."""
from __future__ import annotations

import asyncio
import dataclasses
import hashlib
import json
import logging
import os
import socket
import threading
import time

import pytest
from pymavlink import mavutil

import companion.io.mavlink as M
from companion.io import mavlink_codec
from companion.config import loads_config
from companion.io.mavlink_signing import (DEFAULT_LINK_ID, LinkSigning, SigningKeyError, generate_key_file,
                                          key_file_warning, key_from_text, load_key, sign_encoder,
                                          signing_preflight, signing_timestamp)

mav = mavlink_codec.mavlink2
KEY_HEX = "5c" * 8 + "a1b2c3d4" * 6
KEY = bytes.fromhex(KEY_HEX)
WRONG = bytes(range(1, 33))
MARK_XACC = 123.25            # forged IMU samples carry this; genuine ones never do


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def key_file(tmp_path, text=KEY_HEX, mode=0o600):
    p = tmp_path / "mavlink.key"
    p.write_text(text + "\n")
    p.chmod(mode)
    return p


def peer_conn(port: int, key: bytes | None):
    """The 'autopilot': pymavlink's mavutil over UDP (1/1), signing with pymavlink's own code."""
    c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1,
                                   dialect="ardupilotmega")
    if key is not None:
        c.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda m, msg_id: False, link_id=0)
    return c


def heartbeat():
    return mav.MAVLink_heartbeat_message(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3)


def imu(t_us: int, xacc: float = 0.01):
    return mav.MAVLink_highres_imu_message(t_us, xacc, 0.0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)


def packed(msg, key: bytes | None = None, timestamp: int | None = None, link_id: int = 0) -> bytes:
    """Frame bytes as 1/1 made by a separate encoder: unsigned, or signed with ``key``."""
    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    if key is not None:
        sign_encoder(enc, key, link_id, timestamp)
    return bytes(msg.pack(enc))


def verify(frame: bytes, key: bytes) -> bool:
    """Independent check of a MAVLink 2 signature (mavlink.io: SHA-256(key + frame)[:6])."""
    return len(frame) > 13 and frame[2] & 0x01 and hashlib.sha256(key + frame[:-6]).digest()[:6] == frame[-6:]


async def _wait(pred, timeout=3.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        await asyncio.sleep(0.01)
    return pred()


async def _collect(link, seconds):
    out = []
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        lm = await link.recv(timeout=0.05)
        if lm is not None:
            out.append(lm)
    return out


def _peer_drain(peer) -> list:
    out = []
    while True:
        m = peer.recv_msg()
        if m is None:
            return out
        out.append(m)


def _raw_peer_frames(peer) -> list[bytes]:
    """Every datagram the peer's socket holds, unparsed (to check our signatures independently)."""
    frames = []
    peer.port.setblocking(False)
    while True:
        try:
            frames.append(peer.port.recv(65535))
        except BlockingIOError:
            return frames


async def _linked(port, signing, **kw):
    link = M.MavlinkLink(f"udpin:127.0.0.1:{port}", heartbeat_interval_s=0.1, timesync_interval_s=0,
                         signing=signing, **kw)
    await link.start()
    return link


# ------------------------------------------------------------------------------------ (a) + (b)
def test_signed_peer_is_accepted_and_verifies_our_frames():
    async def main():
        port = free_udp_port()
        link = await _linked(port, LinkSigning(key_from_text(KEY_HEX), required=True))
        peer = peer_conn(port, KEY)
        try:
            peer.mav.send(heartbeat())
            assert await _wait(lambda: link.connected)
            t0 = 5_000_000
            for k in range(20):
                peer.mav.send(imu(t0 + 5000 * k))
            got = [lm for lm in await _collect(link, 0.4) if lm.msg.get_type() == "HIGHRES_IMU"]
            assert [lm.msg.time_usec for lm in got] == [t0 + 5000 * k for k in range(20)]
            assert all(lm.msg.get_signed() for lm in got)
            # the logged bytes are the signed frame, and replay parses them without the key
            assert verify(got[0].raw, KEY) and mavlink_codec.parse_bytes(got[0].raw)[0].time_usec == t0
            h = link.health()
            assert h["signing: good"] >= 21 and h["signing: rejected unsigned"] == 0
            assert h["signing: bad signature"] == 0 and h["bad_data"] == 0
            assert h["signing"] == {"required": True, "key": "hex", "link_id": DEFAULT_LINK_ID, "streams": 1}
            # what we send: every frame signed with the key, our link id, and pymavlink verifies it
            await asyncio.sleep(0.35)                       # a few of our 10 Hz heartbeats
            raw = _raw_peer_frames(peer)
            assert len(raw) >= 3 and all(verify(f, KEY) for f in raw)
            assert all(f[-13] == DEFAULT_LINK_ID for f in raw)
            stamps = [int.from_bytes(f[-12:-6], "little") for f in raw]
            assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
            assert abs(stamps[-1] - signing_timestamp(time.time())) < 5 * 100_000     # the wall clock, 10 us units
            for f in raw:                                   # through the peer's own signing checks
                ms = peer.mav.parse_buffer(f)
                assert ms and ms[0].get_type() != "BAD_DATA" and ms[0].get_signed()
            assert peer.mav.signing.goodsig_count == len(raw) and peer.mav.signing.badsig_count == 0
        finally:
            peer.close()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 20))


def test_forged_wrongly_signed_and_replayed_frames_from_the_same_socket_are_dropped_and_counted():
    async def main():
        port = free_udp_port()
        link = await _linked(port, LinkSigning(key_from_text(KEY_HEX), required=True))
        peer = peer_conn(port, KEY)
        try:
            # a forged unsigned HEARTBEAT first: it must not bring the link up (nor lock the peer)
            peer.write(packed(heartbeat()))
            await asyncio.sleep(0.2)
            assert not link.connected and link.peer_lock.peer is None
            peer.mav.send(heartbeat())
            assert await _wait(lambda: link.connected)
            genuine = packed(imu(1_000_000), KEY, link_id=5)      # a second genuine stream (link 5)
            peer.write(genuine)
            forged = [packed(imu(1_005_000 + 5000 * k, MARK_XACC)) for k in range(10)]              # unsigned
            wrong = [packed(imu(1_100_000 + 5000 * k, MARK_XACC), WRONG) for k in range(5)]         # other key
            v1 = mav.MAVLink(None, srcSystem=1, srcComponent=1)
            v1.seq = 0
            mav1 = bytes(imu(1_200_000, MARK_XACC).pack(v1, force_mavlink1=True))                 # MAVLink 1
            far = bytearray(packed(imu(1_300_000, MARK_XACC), KEY, timestamp=(1 << 48) - 2))
            far[-1] ^= 0xFF                    # bad signature, far-future stamp on the peer's stream (link 0)
            for f in forged + wrong + [mav1, genuine, bytes(far)]:        # genuine again = a replay
                peer.write(f)
            # the genuine stream goes on after all that (the far-future forgery did not poison it)
            for k in range(5):
                peer.mav.send(imu(2_000_000 + 5000 * k))
            got = [lm.msg for lm in await _collect(link, 0.5) if lm.msg.get_type() == "HIGHRES_IMU"]
            assert [m.time_usec for m in got] == [1_000_000] + [2_000_000 + 5000 * k for k in range(5)]
            assert all(m.xacc != MARK_XACC for m in got)
            h = link.health()
            assert h["signing: rejected unsigned"] == 1 + 10 + 1           # heartbeat, IMU, MAVLink 1
            assert h["signing: bad signature"] == 5 + 1
            assert h["signing: replayed"] == 1
            assert h["bad_data"] == 0 and h["heartbeats_rx"] == 1
        finally:
            peer.close()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 20))


def test_forged_frames_change_nothing_the_service_consumes(tmp_path):
    """The same genuine IMU stream through the pipeline, with and without forged unsigned and
    wrongly signed IMU frames interleaved from the same socket: identical solutions."""
    from companion.config import Config
    from companion.pipeline import NavPipeline

    async def run(with_forgeries: bool):
        port = free_udp_port()
        link = await _linked(port, LinkSigning(key_from_text(KEY_HEX), required=True))
        peer = peer_conn(port, KEY)
        pipe = NavPipeline(Config())
        fed = []
        try:
            peer.mav.send(heartbeat())
            assert await _wait(lambda: link.connected)
            peer.mav.send(mav.MAVLink_system_time_message(int(1.7e15), 1000))
            for k in range(200):
                t_us = 1_000_000 + 5000 * k
                peer.mav.send(imu(t_us))
                if with_forgeries:
                    peer.write(packed(imu(t_us + 2500, MARK_XACC)))
                    peer.write(packed(imu(t_us + 2600, MARK_XACC), WRONG))
                if k % 50 == 0:
                    await asyncio.sleep(0.01)
            for lm in await _collect(link, 0.6):
                if lm.msg.get_type() in ("HIGHRES_IMU", "SYSTEM_TIME"):
                    fed.append((lm.msg.get_type(), getattr(lm.msg, "time_usec", 0), lm.msg.xacc
                                if lm.msg.get_type() == "HIGHRES_IMU" else 0.0))
                    pipe.feed_mavlink(lm.t_mono_ns, lm.msg)
            return fed, dict(pipe.counters), link.health()
        finally:
            peer.close()
            await link.close()

    clean, clean_counters, _ = asyncio.run(asyncio.wait_for(run(False), 20))
    dirty, dirty_counters, h = asyncio.run(asyncio.wait_for(run(True), 20))
    assert len(clean) == 201 and dirty == clean
    assert {k: v for k, v in dirty_counters.items() if "imu" in k.lower()} == \
        {k: v for k, v in clean_counters.items() if "imu" in k.lower()}
    assert h["signing: rejected unsigned"] == 200 and h["signing: bad signature"] == 200


# ----------------------------------------------------------------------------------------- (c)
def test_signing_not_required_accepts_unsigned_but_signs_ours_and_drops_bad_signatures():
    async def main():
        port = free_udp_port()
        link = await _linked(port, LinkSigning(key_from_text("correct horse battery staple"), required=False))
        peer = peer_conn(port, None)                      # an autopilot without signing (PX4 v1.15)
        try:
            peer.mav.send(heartbeat())
            assert await _wait(lambda: link.connected)
            for k in range(10):
                peer.mav.send(imu(1_000_000 + 5000 * k))
            peer.write(packed(imu(3_000_000, MARK_XACC), WRONG))    # a signature must be good, always
            got = [lm.msg for lm in await _collect(link, 0.4) if lm.msg.get_type() == "HIGHRES_IMU"]
            assert [m.time_usec for m in got] == [1_000_000 + 5000 * k for k in range(10)]
            h = link.health()
            assert h["signing: accepted unsigned"] == 11 and h["signing: rejected unsigned"] == 0
            assert h["signing: bad signature"] == 1 and h["signing"]["key"] == "passphrase"
            passphrase_key = hashlib.sha256(b"correct horse battery staple").digest()      # MAVProxy's
            raw = _raw_peer_frames(peer)
            assert raw and all(verify(f, passphrase_key) for f in raw)
            # the unsigned peer still reads our signed frames (the trailer is skipped without a key)
            assert all(peer.mav.parse_buffer(f)[0].get_type() == "HEARTBEAT" for f in raw)
        finally:
            peer.close()
            await link.close()

    asyncio.run(asyncio.wait_for(main(), 20))


def test_outgoing_timestamp_follows_the_clock_and_the_newest_seen():
    class Conn:                     # what attach() needs of a mavfile: setup_signing and .mav
        def __init__(self):
            self.mav = mav.MAVLink(None)
            self.mav.robust_parsing = True

        def setup_signing(self, key, sign_outgoing, allow_unsigned_callback, initial_timestamp, link_id):
            s = self.mav.signing
            s.secret_key, s.sign_outgoing, s.allow_unsigned_callback = key, sign_outgoing, allow_unsigned_callback
            s.timestamp, s.link_id = initial_timestamp, link_id

    t = [1.8e9]
    ls = LinkSigning(key_from_text(KEY_HEX), required=True, clock=lambda: t[0])
    conn = Conn()
    ls.attach(conn)
    s = conn.mav.signing
    assert s.timestamp == signing_timestamp(1.8e9)
    t[0] += 30.0
    ls.tick()
    assert s.timestamp == signing_timestamp(1.8e9 + 30.0)
    t[0] -= 3600.0                                        # the clock steps back: we do not
    ls.tick()
    assert s.timestamp == signing_timestamp(1.8e9 + 30.0)
    ahead = signing_timestamp(1.8e9 + 600.0)              # a good frame from a peer 10 min ahead
    frame = packed(heartbeat(), KEY, timestamp=ahead)
    assert conn.mav.parse_buffer(frame)[0].get_type() == "HEARTBEAT"
    assert s.timestamp == ahead
    stale = packed(heartbeat(), KEY, timestamp=ahead - 61 * 100_000, link_id=7)   # new stream, 61 s behind
    assert conn.mav.parse_buffer(stale)[0].get_type() == "BAD_DATA"
    assert ls.counters["signing: stale stream"] == 1


# ----------------------------------------------------------------------------------------- (d)
def test_key_file_formats():
    assert key_from_text(KEY_HEX + "\n").key == KEY and key_from_text(KEY_HEX.upper()).kind == "hex"
    # MAVProxy `signing setup PASS`: key = SHA-256 of the passphrase (mavproxy_signing.passphrase_to_key)
    k = key_from_text("  my pass phrase \n")
    assert k.key == hashlib.sha256(b"my pass phrase").digest() and k.kind == "passphrase"
    assert key_from_text(KEY_HEX[:-1]).kind == "passphrase"          # 63 hex characters: a passphrase
    assert KEY_HEX not in repr(key_from_text(KEY_HEX)) and "pass" not in repr(k.key)


@pytest.mark.parametrize("content, needle", [
    (None, "key file not found"),
    ("", "is empty"),
    ("   \n\n", "is empty"),
    ("00" * 32, "all-zero"),
    (b"\xff\xfe\x00\x01" * 8, "not text"),
    ("line one\nline two\n", "one line"),
    ("dir", "is a directory"),
])
def test_bad_key_file_is_a_clear_error(tmp_path, content, needle):
    p = tmp_path / "k"
    if content == "dir":
        p.mkdir()
    elif isinstance(content, bytes):
        p.write_bytes(content)
    elif content is not None:
        p.write_text(content)
    with pytest.raises(SigningKeyError, match=needle) as ei:
        load_key(p)
    assert str(p) in str(ei.value)
    if isinstance(content, str) and content.strip() and content != "dir":
        assert content.strip().splitlines()[0] not in str(ei.value)        # the content never


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a mode-000 file")
def test_unreadable_key_file(tmp_path):
    p = key_file(tmp_path, mode=0o000)
    with pytest.raises(SigningKeyError, match="not readable"):
        load_key(p)


def test_key_file_permissions_warning_and_generation(tmp_path):
    p = tmp_path / "new.key"
    assert generate_key_file(p) is True
    assert (p.stat().st_mode & 0o777) == 0o600 and key_file_warning(p) is None
    k = load_key(p)
    assert k.kind == "hex" and len(k.key) == 32 and any(k.key)
    before = p.read_bytes()
    assert generate_key_file(p) is False and p.read_bytes() == before        # never overwritten
    assert generate_key_file(tmp_path / "other.key") and load_key(tmp_path / "other.key").key != k.key
    p.chmod(0o644)
    w = key_file_warning(p)
    assert w and "0644" in w and "chmod 600" in w and before.decode().strip() not in w


def test_config_keys_and_their_checks(tmp_path):
    from companion.config import ConfigError
    with pytest.raises(ConfigError, match="mavlink.signing_required: needs mavlink.signing_key_file"):
        loads_config("[mavlink]\nsigning_required = true\n")
    cfg = loads_config(f"[mavlink]\nsigning_key_file = '{tmp_path / 'missing.key'}'\nsigning_required = true\n")
    with pytest.raises(SigningKeyError, match="not found"):
        signing_preflight(cfg)
    with pytest.raises(SigningKeyError, match="not found"):
        M.link_from_config(cfg.mavlink)
    p = key_file(tmp_path, mode=0o640)
    cfg = loads_config(f"[mavlink]\nsigning_key_file = '{p}'\nsigning_required = true\n")
    assert "readable or writable by other users" in signing_preflight(cfg)
    link = M.link_from_config(cfg.mavlink)
    assert link.signing.required and link.signing.kind == "hex"
    assert signing_preflight(loads_config("")) is None and M.link_from_config(loads_config("").mavlink).signing is None


def test_run_and_config_check_refuse_a_missing_key_file(tmp_path, capsys):
    from companion.cli import main
    c = tmp_path / "c.toml"
    c.write_text(f"[mavlink]\nsigning_key_file = '{tmp_path / 'gone.key'}'\n")
    assert main(["run", "--config", str(c)]) == 2
    err = capsys.readouterr().err
    assert f"error: {tmp_path / 'gone.key'}: MAVLink signing key file not found" in err and "Traceback" not in err
    assert main(["config", "check", str(c)]) == 2
    assert "signing key file not found" in capsys.readouterr().err
    from companion.service import Service                      # the service itself refuses too
    with pytest.raises(SigningKeyError):
        asyncio.run(Service(loads_config(c.read_text()), install_signal_handlers=False).run())


def test_the_key_is_in_no_log_line_field_log_or_health_report(tmp_path, caplog):
    from companion.service import redacted_config_event
    passphrase = "never-print-me-9f3a"
    p = key_file(tmp_path, passphrase)
    cfg = loads_config(f"[mavlink]\nsigning_key_file = '{p}'\nsigning_required = true\n")
    secret_forms = (passphrase, hashlib.sha256(passphrase.encode()).hexdigest(),
                    hashlib.sha256(passphrase.encode()).hexdigest().upper())

    async def main():
        port = free_udp_port()
        link = M.link_from_config(dataclasses.replace(cfg.mavlink, connection=f"udpin:127.0.0.1:{port}"))
        await link.start()
        peer = peer_conn(port, WRONG)
        try:
            for k in range(5):
                peer.mav.send(heartbeat())
                peer.write(packed(imu(10_000 + k)))
            await asyncio.sleep(0.3)
            link.signing._last_warn = -1e9
            link.signing.tick()                          # the rate-limited drop warning, now
            return link.health()
        finally:
            peer.close()
            await link.close()

    with caplog.at_level(logging.DEBUG):
        h = asyncio.run(asyncio.wait_for(main(), 20))
    text = caplog.text + json.dumps(h) + redacted_config_event(cfg).decode() + repr(cfg)
    assert "MAVLink signing dropped frames" in caplog.text and "MAVLink 2 signing on" in caplog.text
    assert h["signing: bad signature"] == 5 and h["signing: rejected unsigned"] == 5
    assert str(p) in redacted_config_event(cfg).decode()                # the path is fine to keep
    for s in secret_forms:
        assert s not in text


# ------------------------------------------------------------------ companion signing setup (CLI)
class _FakeAutopilot(threading.Thread):
    """pymavlink udpin 'autopilot' 1/1 sending HEARTBEAT at 10 Hz; ``takes_key``: on SETUP_SIGNING it
    signs from then on with that key (what ArduPilot's handle_setup_signing does)."""

    def __init__(self, port: int, takes_key: bool):
        super().__init__(daemon=True)
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1,
                                               dialect="ardupilotmega")
        self.takes_key = takes_key
        self.setup: list = []
        self.stop = threading.Event()

    def run(self):
        next_hb = 0.0
        while not self.stop.is_set():
            m = self.conn.recv_msg()
            if m is not None and m.get_type() == "SETUP_SIGNING":
                self.setup.append(m)
                if self.takes_key:
                    self.conn.setup_signing(bytes(m.secret_key), sign_outgoing=True,
                                            allow_unsigned_callback=lambda *_: True,
                                            initial_timestamp=m.initial_timestamp, link_id=0)
            if time.monotonic() > next_hb:            # to whoever spoke last (none yet: nowhere)
                self.conn.mav.send(heartbeat())
                next_hb = time.monotonic() + 0.1
            if m is None:
                time.sleep(0.005)
        self.conn.close()


@pytest.mark.parametrize("takes_key", [True, False])
def test_signing_setup_command(tmp_path, capsys, takes_key):
    from companion.cli import main
    kf = tmp_path / "k.key"
    assert main(["signing", "setup", "--key-file", str(kf)]) == 0
    assert "new MAVLink signing key" in capsys.readouterr().out and (kf.stat().st_mode & 0o777) == 0o600
    port = free_udp_port()
    ap = _FakeAutopilot(port, takes_key)
    ap.start()
    try:
        rc = main(["signing", "setup", "--key-file", str(kf), "--connection", f"udpout:127.0.0.1:{port}",
                   "--timeout", "2"])
    finally:
        ap.stop.set()
        ap.join(5)
    out = capsys.readouterr()
    assert len(ap.setup) == 1
    s = ap.setup[0]
    assert bytes(s.secret_key) == load_key(kf).key and (s.target_system, s.target_component) == (1, 1)
    assert abs(s.initial_timestamp - signing_timestamp(time.time())) < 30 * 100_000
    if takes_key:
        assert rc == 0 and "signs with this key" in out.out
    else:
        assert rc == 1 and "did not take it" in out.err
    assert kf.read_text().strip() not in out.out + out.err


def test_service_warns_and_counts_a_key_file_readable_by_others(tmp_path, caplog):
    from companion.service import Service
    p = key_file(tmp_path, mode=0o644)
    port = free_udp_port()
    cfg = loads_config(f"[mavlink]\nconnection = 'udpin:127.0.0.1:{port}'\nsigning_key_file = '{p}'\n"
                       f"[log]\nenabled = false\n")
    svc = Service(cfg, install_signal_handlers=False)

    async def run():
        task = asyncio.create_task(svc.run())
        await asyncio.sleep(0.3)
        h = svc.health()
        svc.stop()
        await task
        return h
    with caplog.at_level(logging.WARNING):
        h = asyncio.run(asyncio.wait_for(run(), 20))
    assert svc.counters["signing key file readable by others"] == 1
    assert any("MAVLink signing key file is readable" in r.getMessage() and str(p) in r.getMessage()
               for r in caplog.records)
    assert h["link"]["signing"]["required"] is False and KEY_HEX not in json.dumps(h, default=str)
