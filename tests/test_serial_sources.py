"""Correction sources on real file descriptors: a serial radio on a pty pair (os.openpty), a
recorded file, and the CorrectionPipeline that turns their bytes into core messages and
GPS_RTCM_DATA forwarding."""
from __future__ import annotations

import asyncio
import os
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from companion.io import mavlink_codec
from companion.io import mavlink_encode
from companion.config import loads_config
from companion.io.corrections import (CorrectionPipeline, FileCorrectionSource, SerialCorrectionSource,
                                      correction_source_from_config)
from companion.io.rtcm import GpsRtcmDataFragmenter, decode_rtcm_file
from companion.messages import BaseStationPosition, GnssEpoch, GpsEphemeris
from tests._data import data_path

RTCM_FILE = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm")
ARP = np.array([-3551876.8287, 3887786.8598, 3586946.3873])


@pytest.mark.real_data
def test_serial_radio_on_pty_to_core_messages_and_forwarding():
    data = RTCM_FILE.read_bytes()[:50000]
    master, slave = os.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)

    async def main():
        src = SerialCorrectionSource(name, 57600, reopen_interval_s=0.1)
        fragmenter = GpsRtcmDataFragmenter()
        forwarded = []
        pipe = CorrectionPipeline(src, week_hint=2240,
                                  forward=lambda f: forwarded.extend(mavlink_encode.gps_rtcm_data_messages(f, fragmenter)))
        msgs, raw = [], bytearray()

        async def consume():
            async for batch in pipe.stream():
                raw.extend(batch.raw)
                msgs.extend(batch.messages)
                if len(raw) >= len(data):
                    return

        async def radio():
            for i in range(0, len(data), 700):           # a 57600 baud radio in bursts
                os.write(master, data[i:i + 700])
                await asyncio.sleep(0.002)
        await asyncio.wait_for(asyncio.gather(consume(), radio()), 15)
        return pipe, msgs, bytes(raw), forwarded

    try:
        pipe, msgs, raw, forwarded = asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)
    assert raw == data                                   # raw chunks are what the field log gets
    ref, _ = decode_rtcm_file(str(RTCM_FILE), week_hint=2240)
    epochs = [m for m in msgs if isinstance(m, GnssEpoch)]
    assert any(isinstance(m, BaseStationPosition) and np.allclose(m.r_e, ARP, atol=1e-3) for m in msgs)
    ref_epochs = [m for m in ref if isinstance(m, GnssEpoch)]
    assert len(epochs) >= 10
    assert [e.t_gps for e in epochs] == [e.t_gps for e in ref_epochs[:len(epochs)]]
    assert all(e.source == "base" for e in epochs)
    # every frame went to the forwarder as GPS_RTCM_DATA; reassembled they are the frames again
    assert pipe.counters["forwarded"] == pipe.counters["frames"] > 50
    back = [mavlink_codec.parse_bytes(mavlink_codec.pack(x))[0] for x in forwarded]
    assert all(b.get_type() == "GPS_RTCM_DATA" for b in back)


def test_serial_source_reopens_after_port_loss(tmp_path):
    """The radio is reached through a symlink (as udev's /dev/serial/by-id); it disappears (pty
    master closed: EIO) and comes back as a new pty behind the same name."""
    link = tmp_path / "radio"

    def new_pty():
        master, slave = os.openpty()
        tty.setraw(slave)
        if link.is_symlink():
            link.unlink()
        link.symlink_to(os.ttyname(slave))
        return master, slave

    async def main():
        master, slave = new_pty()
        src = SerialCorrectionSource(str(link), 57600, reopen_interval_s=0.05)
        got = bytearray()

        async def consume():
            async for chunk in src.stream():
                got.extend(chunk)
        task = asyncio.create_task(consume())
        await asyncio.sleep(0.1)
        os.write(master, b"\xd3\x00\x00abc")
        t_end = time.monotonic() + 3
        while len(got) < 6 and time.monotonic() < t_end:
            await asyncio.sleep(0.01)
        os.close(master)                                  # the radio goes away: EIO on read
        os.close(slave)
        t_end = time.monotonic() + 3
        while src.counters["errors"] < 2 and time.monotonic() < t_end:
            await asyncio.sleep(0.02)
        master, slave = new_pty()                         # ... and comes back
        t_end = time.monotonic() + 3
        while src.counters["opens"] < 2 and time.monotonic() < t_end:
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.05)
        os.write(master, b"xyz")
        t_end = time.monotonic() + 3
        while len(got) < 9 and time.monotonic() < t_end:
            await asyncio.sleep(0.01)
        task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass
        os.close(master)
        os.close(slave)
        return src, bytes(got)

    src, got = asyncio.run(asyncio.wait_for(main(), 10))
    assert got == b"\xd3\x00\x00abcxyz"
    assert src.counters["errors"] >= 1 and src.counters["opens"] == 2


@pytest.mark.real_data
def test_file_source_paced_and_fast_and_base_override():
    async def run(source, override=None):
        pipe = CorrectionPipeline(source, week_hint=2240, base_position_ecef_m=override)
        out = []
        t0 = time.monotonic()
        async for batch in pipe.stream():
            out.extend(batch.messages)
        return out, time.monotonic() - t0

    fast, _ = asyncio.run(run(FileCorrectionSource(RTCM_FILE, realtime=False)))
    ref, _ = decode_rtcm_file(str(RTCM_FILE), week_hint=2240)
    assert [type(m).__name__ for m in fast] == [type(m).__name__ for m in ref]
    assert any(isinstance(m, GpsEphemeris) for m in fast)
    # paced: 20 kB at 40 kB/s takes ~0.5 s
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"rtcm-head-{os.getpid()}.rtcm"
    tmp.write_bytes(RTCM_FILE.read_bytes()[:20000])
    try:
        paced, dt = asyncio.run(run(FileCorrectionSource(tmp, realtime=True, rate_bps=40000), override=[1.0, 2.0, 3.0]))
    finally:
        tmp.unlink()
    assert 0.4 < dt < 1.5
    bases = [m for m in paced if isinstance(m, BaseStationPosition)]
    assert bases and all(np.allclose(b.r_e, [1.0, 2.0, 3.0]) for b in bases)
    assert isinstance(paced[0], BaseStationPosition)      # the override comes first


def test_sources_from_config():
    cfg = loads_config('[corrections]\nsource = "file"\n[corrections.file]\npath = "/x.rtcm"\nrealtime = false\n')
    src = correction_source_from_config(cfg.corrections)
    assert isinstance(src, FileCorrectionSource) and not src.realtime
    cfg = loads_config('[corrections]\nsource = "ntrip"\n[corrections.ntrip]\nmountpoint = "M"\nversion = 1\n')
    src = correction_source_from_config(cfg.corrections, position_cb=lambda: None)
    assert src.version == 1 and src.mountpoint == "M"
    assert correction_source_from_config(loads_config("").corrections) is None
