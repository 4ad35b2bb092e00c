"""The service under hostile input and resource limits (issue 14), without a flight: the service
object's own steps with a fake link, a fake correction source and a fake full disk."""
from __future__ import annotations

import asyncio
import logging
import os

import pytest

from companion.config import load_config, loads_config
from companion.io.fieldlog import FieldLogWriter, read_field_log
from companion.pipeline import NavPipeline
from companion.service import DEFAULT_MAX_BYTES_PER_TURN, Service, redacted_config_event
from tests._data import data_path

RTCM = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm")
SECRET = "s3cret-Pa55"

TOML = f"""
[corrections]
source = "file"
[corrections.file]
path = "{RTCM}"
realtime = false
[corrections.ntrip]
host = "caster.example"
user = "rover"
password = "{SECRET}"
"""


class FakeLink:
    connected = True

    def __init__(self):
        self.sent = []

    def send(self, msg):
        self.sent.append(msg)
        return True

    def health(self):
        return {"connected": True}

    def statustexts(self):
        return [bytes(m.text).decode("ascii", "replace").rstrip("\x00") if isinstance(m.text, (bytes, bytearray))
                else m.text for m in self.sent if m.get_type() == "STATUSTEXT"]


def _service(tmp_path, text=TOML):
    cfg = loads_config(text + f'\n[log]\ndir = "{tmp_path / "log"}"\n')
    return Service(cfg, install_signal_handlers=False)


class FullDisk:
    def __init__(self):
        self.full = False

    def __call__(self, fd, data):
        if self.full:
            raise OSError(28, "No space left on device")
        return os.write(fd, data)


# -- secrets -----------------------------------------------------------------------------------
def test_config_copy_in_the_field_log_has_no_password_and_still_replays(tmp_path):
    svc = _service(tmp_path)
    ev = redacted_config_event(svc.cfg)
    assert SECRET.encode() not in ev
    from companion.replay import _config_from_event
    cfg = _config_from_event(ev)
    assert cfg.corrections.ntrip.user == "rover" and cfg.corrections.ntrip.password != SECRET
    NavPipeline(cfg)                                 # replay can build its pipeline from it

    async def run():
        task = asyncio.create_task(svc.run())
        await asyncio.sleep(1.0)
        svc.stop()
        await task
    asyncio.run(run())
    blobs = b"".join(p.read_bytes() for p in (tmp_path / "log").glob("*.cflog"))
    assert blobs and SECRET.encode() not in blobs
    kinds = [r.kind for r in read_field_log(tmp_path / "log")]
    assert kinds[0] == "event" and "rtcm" in kinds


def test_service_warns_when_the_config_file_is_readable_by_others(tmp_path, caplog):
    path = tmp_path / "companion.toml"
    path.write_text(TOML + f'\n[log]\nenabled = false\ndir = "{tmp_path / "log"}"\n')
    os.chmod(path, 0o644)
    svc = Service(load_config(path), install_signal_handlers=False)

    async def run():
        task = asyncio.create_task(svc.run())
        await asyncio.sleep(0.2)
        svc.stop()
        await task
    with caplog.at_level(logging.WARNING):
        asyncio.run(run())
    assert any("readable" in r.getMessage() and str(path) in r.getMessage() for r in caplog.records)
    assert svc.counters["config file readable by others"] == 1
    os.chmod(path, 0o600)
    caplog.clear()
    svc = Service(load_config(path), install_signal_handlers=False)
    with caplog.at_level(logging.WARNING):
        asyncio.run(run())
    assert not any("readable" in r.getMessage() for r in caplog.records)


# -- disk full ---------------------------------------------------------------------------------
def test_disk_full_is_one_error_one_statustext_and_navigation_goes_on(tmp_path, caplog):
    svc = _service(tmp_path)
    svc.link = FakeLink()
    svc.fieldlog = FieldLogWriter(tmp_path / "log", background_flush=False, fsync_interval_s=0.0,
                                  retry_interval_s=0.0)
    disk = FullDisk()
    svc.fieldlog._os_write = disk
    data = RTCM.read_bytes()[:60000]
    chunks = [data[i:i + 400] for i in range(0, len(data), 400)]
    disk.full = True
    with caplog.at_level(logging.INFO):
        for k, c in enumerate(chunks[:100]):
            svc._correction_slice(c, None)
            if k % 10 == 0:
                svc._announce_fieldlog()
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1, [r.getMessage() for r in errors]
    st = svc.link.statustexts()
    assert len(st) == 1 and "disk full" in st[0]
    # navigation unaffected: every chunk reached the pipeline although none was logged
    assert svc.pipeline.counters["records rtcm"] == 100
    assert svc.pipeline.rtcm.counters["frames"] > 50
    assert svc.counters["field log records dropped"] == 100
    assert svc.health()["field_log"]["paused"]
    disk.full = False
    for c in chunks[100:110]:
        svc._correction_slice(c, None)
    svc._announce_fieldlog()
    st = svc.link.statustexts()
    assert len(st) == 2 and "resumed" in st[1]
    assert svc.counters["field log paused"] == 1 and svc.counters["field log resumed"] == 1
    svc.fieldlog.close()
    assert sum(1 for r in read_field_log(tmp_path / "log") if r.kind == "rtcm") >= 9


# -- corrections: rate cap and slices ----------------------------------------------------------
def test_correction_flood_over_the_rate_cap_is_dropped_counted_and_logged_once(tmp_path, caplog):
    svc = _service(tmp_path)
    chunk = b"\xd3\x03" * 2048
    with caplog.at_level(logging.WARNING, logger="companion.service"):
        admitted = sum(len(chunk) for _ in range(250) if svc._admit("rtcm", chunk))
    cap = svc._caps["rtcm"]
    assert admitted <= cap.burst_bytes + cap.rate_bps * 1.0     # burst + what a second can add
    assert svc.counters["rtcm dropped: rate cap"] >= 200
    assert svc.counters["rtcm bytes dropped: rate cap"] == 250 * len(chunk) - admitted
    assert len([r for r in caplog.records if "dropped" in r.getMessage()]) == 1
    assert svc.health()["rate_caps"]["rtcm"]["dropped_chunks"] >= 200


class OneBurst:
    """A correction source that delivers one large chunk, then ends."""
    name = "burst"
    counters: dict = {}

    def __init__(self, data):
        self.data = data

    async def stream(self):
        yield self.data


def test_a_correction_burst_is_handled_in_slices_with_the_loop_turning_between(tmp_path, monkeypatch):
    svc = _service(tmp_path)
    data = RTCM.read_bytes()[:8192]
    import companion.io.corrections as corr
    monkeypatch.setattr(corr, "correction_source_from_config", lambda c, position_cb=None: OneBurst(data))
    ticks = []

    async def run():
        done = False

        async def ticker():          # stands in for the IMU path: counts the turns it gets
            while not done:
                ticks.append(svc.record_counts["rtcm"])
                await asyncio.sleep(0)
        t = asyncio.create_task(ticker())
        await svc._corrections_task()
        done = True
        await t
    asyncio.run(run())
    n_slices = -(-len(data) // DEFAULT_MAX_BYTES_PER_TURN)
    assert svc.record_counts["rtcm"] == n_slices == 16
    assert svc.record_bytes["rtcm"] == len(data)
    # the ticker got a turn after every slice: it saw every count from the first to the last
    assert set(range(1, n_slices + 1)) <= set(ticks)


# -- RTCM before the first IMU sample ----------------------------------------------------------
def test_rtcm_before_the_first_imu_sample_is_counted_not_a_traceback_per_frame(caplog):
    cfg = loads_config(TOML)
    pipe = NavPipeline(cfg)
    data = RTCM.read_bytes()[:40000]
    with caplog.at_level(logging.WARNING):
        for i in range(0, len(data), 1024):
            pipe.feed("rtcm", 0, data[i:i + 1024])
    assert pipe.rtcm.counters["no_time_reference"] > 20
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert not any(k.startswith("pipeline exceptions") for k in pipe.counters)


@pytest.mark.parametrize("n", [1, 3])
def test_service_fsync_interval_never_exceeds_the_kill9_margin(tmp_path, n):
    text = TOML + f'\n[log]\ndir = "{tmp_path / "log"}"\nfsync_interval_s = {float(n)}\n'
    svc = Service(loads_config(text), install_signal_handlers=False)

    async def run():
        task = asyncio.create_task(svc.run())
        await asyncio.sleep(0.2)
        assert svc.fieldlog.fsync_interval_s <= 0.5
        svc.stop()
        await task
    asyncio.run(run())
