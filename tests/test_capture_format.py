"""Telling a binary capture (RTCM 3, UBX) from a RINEX file when the capture does not start on a
frame (companion.io.capture_format).  The real Hiroshima base capture (str2str) starts with 12
bytes of a frame's tail: `companion gnss --mode rtk --base` took it for a RINEX file and asked for
--nav, then failed to read it, before the check looked for a checksummed frame instead of a
preamble at byte 0."""
from __future__ import annotations

import os

import pytest

from companion.io.capture_format import SCAN_BYTES, is_rtcm_capture, is_ubx_capture
from tests._data import data_path

H = data_path("qzsl6tool-hiroshima-rtcm3-ubx")
RTCM_MID_FRAME = H / "20221213-010900.rtcm"
UBX = H / "20230919-114418.ubx"


def test_real_captures_are_told_apart_even_from_mid_frame():
    assert RTCM_MID_FRAME.read_bytes()[0] != 0xD3                  # the capture starts mid-frame
    assert is_rtcm_capture(RTCM_MID_FRAME) and not is_ubx_capture(RTCM_MID_FRAME)
    assert is_ubx_capture(UBX) and not is_rtcm_capture(UBX)


@pytest.mark.parametrize("cut", [1, 5, 37, 1001])
def test_a_capture_cut_anywhere_is_still_one(tmp_path, cut):
    for src, check in ((UBX, is_ubx_capture), (RTCM_MID_FRAME, is_rtcm_capture)):
        f = tmp_path / f"cut{cut}{src.suffix}"
        f.write_bytes(src.read_bytes()[cut:cut + 50_000])
        assert check(f), (src.name, cut)


def test_rinex_text_compressed_rinex_and_noise_are_not_captures(tmp_path):
    for f in (data_path("rtklib-testdata-geonet-2005") / "rinex" / "07590920.05o",
              data_path("matrtklib-septentrio-static-2024") / "rover.crx.gz",
              data_path("cssrlib-fujisawa-car-2021") / "nav.rnx.gz"):
        assert not is_rtcm_capture(f) and not is_ubx_capture(f), f.name
    noise = tmp_path / "noise.bin"
    noise.write_bytes(os.urandom(4 * SCAN_BYTES))
    assert not is_rtcm_capture(noise) and not is_ubx_capture(noise)
    # frames beyond the scanned head are not looked for: a capture is frames from its start
    late = tmp_path / "late.bin"
    late.write_bytes(b"\x00" * (SCAN_BYTES + 10) + UBX.read_bytes()[:4000])
    assert not is_ubx_capture(late)
