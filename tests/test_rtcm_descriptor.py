"""RTCM 1007 / 1008 / 1033: what the base says it is, from a real stream and from hostile frames, in
the health report, the status page and ``companion gnss --mode rtk``."""
from __future__ import annotations

import pytest

from companion.io.rtcm import RtcmDecoder, decode_rtcm_file
from companion.io.rtcm_descriptor import MAX_DESCRIPTOR_CHARS
from companion.status_page import StatusBoard
from tests._data import data_path
from tests.fuzz_targets import rtcm_frame

pytestmark = pytest.mark.real_data

CAPTURE = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"


def _descriptor_payload(mtype: int, station: int, antenna: bytes, serial: bytes = b"", receiver: bytes = b"",
                        firmware: bytes = b"", receiver_serial: bytes = b"", counts=None) -> bytes:
    """A 1007 / 1008 / 1033 payload: after the 24-bit header every field is whole bytes (DF029-DF232)."""
    counts = counts or {}

    def text(name, s):
        return bytes([counts.get(name, len(s))]) + s
    out = ((mtype << 12) | station).to_bytes(3, "big") + text("antenna", antenna) + bytes([0])
    if mtype in (1008, 1033):
        out += text("serial", serial)
    if mtype == 1033:
        out += text("receiver", receiver) + text("firmware", firmware) + text("receiver_serial", receiver_serial)
    return out


def test_the_real_novatel_base_says_what_it_is():
    _, dec = decode_rtcm_file(str(CAPTURE), week_hint=2240)
    d = dec.base_descriptor
    assert (d.receiver, d.firmware, d.antenna, d.message) == ("NOV OEM729", "OM7MR0810RN0000", "JAVGRANT_G5T NONE", 1033)
    assert dec.counters["descriptor"] == 54                     # every 1033 of the capture counted


def test_a_hostile_descriptor_reaches_nobody_with_control_characters():
    dec = RtcmDecoder(week_hint=2240)
    evil = b"\x1b[2J\x1b]0;pwned\x07" + b"A" * 40
    frame = rtcm_frame(_descriptor_payload(1033, 5, evil, receiver=b"REC\r\nFAKE", firmware=b"\x00\xff1.0"))
    assert dec.feed(frame) == []                                  # kept, not emitted, no exception
    d = dec.base_descriptor
    assert all(" " <= c <= "~" for c in d.antenna + d.receiver + d.firmware)
    assert len(d.antenna) <= MAX_DESCRIPTOR_CHARS and d.receiver == "RECFAKE" and d.firmware == "1.0"
    # a count longer than the frame: a bad payload, counted, the last good descriptor stays
    short = rtcm_frame(_descriptor_payload(1033, 5, b"AB", counts={"antenna": 200}))
    dec.feed(short)
    assert dec.counters.get("bad_payload", 0) == 1 and dec.base_descriptor == d


def test_a_1007_between_1033s_keeps_the_receiver_type():
    dec = RtcmDecoder(week_hint=2240)
    dec.feed(rtcm_frame(_descriptor_payload(1033, 3, b"TRM59800.00 NONE", b"123", b"TRIMBLE NETR9", b"5.45")))
    dec.feed(rtcm_frame(_descriptor_payload(1007, 3, b"TRM59800.00 NONE")))
    d = dec.base_descriptor
    assert (d.receiver, d.firmware, d.antenna, d.antenna_serial) == ("TRIMBLE NETR9", "5.45", "TRM59800.00 NONE", "123")
    dec.feed(rtcm_frame(_descriptor_payload(1007, 4, b"LEIAR25.R4 LEIT")))       # another station: all new
    assert (dec.base_descriptor.station_id, dec.base_descriptor.receiver) == (4, "")


def test_the_simulated_base_says_what_it_is_in_frames_pyrtcm_reads():
    from pyrtcm import RTCMReader

    from sitl.caster import SITL_BASE_RECEIVER, encode_1033
    raw = encode_1033(7, receiver_serial="0001")
    msg = RTCMReader.parse(raw)                                    # the reference parser agrees
    assert (msg.identity, msg.DF003, msg.DF227, msg.DF231) == ("1033", 7, len(SITL_BASE_RECEIVER), 4)
    dec = RtcmDecoder(week_hint=2240)
    dec.feed(raw)
    d = dec.base_descriptor
    assert (d.station_id, d.receiver, d.antenna, d.receiver_serial, d.message) == (7, SITL_BASE_RECEIVER, "NONE NONE",
                                                                                  "0001", 1033)
    with pytest.raises(ValueError, match="31 characters"):
        encode_1033(7, receiver="X" * 32)


def test_the_health_report_and_the_status_page_name_the_base():
    from companion.config import Config
    from companion.pipeline import NavPipeline
    pipe = NavPipeline(Config())
    pipe.rtcm.feed(CAPTURE.read_bytes()[:200_000])
    h = pipe.health()
    assert h["rtcm_base"]["receiver"] == "NOV OEM729" and h["rtcm_base"]["antenna"] == "JAVGRANT_G5T NONE"
    board = StatusBoard()
    board.set_health(h)
    assert board.snapshot()["base"] == "NOV OEM729 / JAVGRANT_G5T NONE"
    assert h["rtcm"]["descriptor"] >= 1


def test_the_antenna_the_base_names_gets_its_calibration(tmp_path):
    """[filter] rtk_antennas: the type a real base's 1033 names (JAVGRANT_G5T NONE) is looked up in
    the file as the stream brings it, and the health report says which calibration each receiver
    has; a base named nothing, or a type not in the file, keeps its phase centres at its ARP."""
    from companion.config import loads_config
    from companion.pipeline import NavPipeline
    from tests.test_rtk_antennas import _antex_text
    atx = tmp_path / "ant.atx"
    atx.write_text(_antex_text({"JAVGRANT_G5T    NONE": (0.0, {"G01": ([0.0, 0.0, 60.0], [0.0] * 19, None)})}))
    pipe = NavPipeline(loads_config(f"[filter]\nrtk_enabled = true\nrtk_antennas = '{atx}'\n"
                                    f"[corrections]\nsource = 'file'\n[corrections.file]\npath = 'base.rtcm3'\n"))
    assert pipe.health()["rtk_antennas"]["base"]["calibration"] is None
    pipe.feed("rtcm", 1_000_000_000, CAPTURE.read_bytes()[:200_000])
    ant = pipe.health()["rtk_antennas"]
    assert ant["base"]["type"] == "JAVGRANT_G5T NONE" and ant["base"]["calibration"] == "ant.atx: JAVGRANT_G5T    NONE"
    assert ant["rover"]["calibration"] is None and "rtk_rover_antenna" in ant["rover"]["notes"][0]
    assert pipe.engine.rtk.base_antenna is not None
    assert pipe.engine.counters["rtk base antenna calibration changes"] == 1
    board = StatusBoard()
    board.set_health(pipe.health())
    assert board.snapshot()["base"] == "NOV OEM729 / JAVGRANT_G5T NONE (calibrated)"
    pipe.engine.name_base_antenna("LEIAR25.R4 LEIT")            # (another base) not in the file
    assert pipe.engine.rtk.base_antenna is None
    assert "not in the file" in pipe.health()["rtk_antennas"]["base"]["notes"][0]


def test_antenna_calibrations_are_checked_at_start_and_found_again_by_a_replay(tmp_path, capsys):
    """The service does not start on a calibration file it cannot read or a type it lacks
    (``companion config check`` says so too); the field log's config record carries the file's
    SHA-256, and a replay elsewhere uses the file where it is given, says when it is another one,
    and runs uncalibrated, saying so, when it has none."""
    import json

    from companion.config import loads_config
    from companion.config_cli import cmd_check
    from companion.nav.rtk_antennas import antennas_preflight, for_replay
    from companion.log_records import config_event
    from tests.test_rtk_antennas import _antex_text
    atx = tmp_path / "ant.atx"
    atx.write_text(_antex_text({"JAVGRANT_G5T    NONE": (0.0, {"G01": ([0.0, 0.0, 60.0], [0.0] * 19, None)})}))
    base = "[corrections]\nsource = 'file'\n[corrections.file]\npath = 'base.rtcm3'\n[filter]\nrtk_enabled = true\n"
    cfg = loads_config(base + f"rtk_antennas = '{atx}'\n")
    assert antennas_preflight(cfg) is None
    for extra, needle in ((f"rtk_antennas = '{tmp_path / 'none.atx'}'\n", "cannot read"),
                          (f"rtk_antennas = '{atx}'\nrtk_rover_antenna = 'TRM59800.00 SCIS'\n", "is not in")):
        toml = tmp_path / "c.toml"
        toml.write_text(base + extra)
        assert needle in antennas_preflight(loads_config(toml.read_text()))
        assert cmd_check(type("A", (), {"files": [str(toml)]})()) == 2
        assert needle in capsys.readouterr().err
    logged = json.loads(config_event(cfg))["rtk_antennas_sha256"]
    same, note = for_replay(cfg, logged)
    assert same.filter.rtk_antennas == str(atx) and note is None
    moved = tmp_path / "elsewhere.atx"
    moved.write_bytes(atx.read_bytes())
    atx.unlink()
    off, note = for_replay(cfg, logged)
    assert off.filter.rtk_antennas == "" and "replayed without them" in note
    found, note = for_replay(cfg, logged, str(moved))
    assert found.filter.rtk_antennas == str(moved) and note is None
    moved.write_text(moved.read_text().replace("60.00", "61.00"))
    _, note = for_replay(cfg, logged, str(moved))
    assert "is not the antenna calibration file the log was made with" in note
