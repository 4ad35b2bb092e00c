"""`companion export LOG --ubx --rtcm` (issue 15): a receiver on the companion's own serial port
and a base's corrections come out of the field log decodable by pyubx2 / pyrtcm and convertible
by RTKLIB's convbin; through the tunnel only the GPS port's replies make the UBX stream."""
from __future__ import annotations

import os
import shutil
import subprocess
from collections import Counter
from itertools import zip_longest

import pytest

from companion.cli import main
from companion.io.fieldlog import FieldLogWriter
from tests._data import data_path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as m  # noqa: E402

pyubx2 = pytest.importorskip("pyubx2")
pyrtcm = pytest.importorskip("pyrtcm")
D = data_path("qzsl6tool-hiroshima-rtcm3-ubx")
UBX, RTCM = D / "20230919-114418.ubx", D / "20221213-010900.rtcm"
RTCM_DATE = ("2022/12/13", "01:09:00")          # the recording's start (file name): RTCM 3 has no week
pytestmark = pytest.mark.real_data


def _ubx_identities(path) -> Counter:
    with open(path, "rb") as fh:
        return Counter(msg.identity for _, msg in pyubx2.UBXReader(fh, protfilter=pyubx2.UBX_PROTOCOL,
                                                                   quitonerror=pyubx2.ERR_IGNORE)
                       if msg is not None)


def _rtcm_identities(path) -> Counter:
    with open(path, "rb") as fh:
        return Counter(msg.identity for _, msg in pyrtcm.RTCMReader(fh, quitonerror=pyrtcm.ERR_IGNORE)
                       if msg is not None)


def _rinex_epochs(path) -> int:
    return sum(1 for ln in path.read_text().splitlines() if ln.startswith(">"))


def test_local_serial_receiver_and_corrections_decode_and_convert(tmp_path):
    ubx, rtcm = UBX.read_bytes()[:80000], RTCM.read_bytes()[:40000]
    w = FieldLogWriter(tmp_path / "log", background_flush=False)
    t = 0
    # interleaved as the service logs them: serial reads of any size, correction chunks
    for i, j in zip_longest(range(0, len(ubx), 1500), range(0, len(rtcm), 750)):
        t += 1000
        if i is not None:
            w.write("ubx", ubx[i:i + 1500], t, t)
        if j is not None:
            w.write("rtcm", rtcm[j:j + 750], t, t)
    w.close()
    src_ubx, src_rtcm = tmp_path / "src.ubx", tmp_path / "src.rtcm3"
    src_ubx.write_bytes(ubx)
    src_rtcm.write_bytes(rtcm)
    out_ubx, out_rtcm = tmp_path / "rover.ubx", tmp_path / "base.rtcm3"
    assert main(["export", str(tmp_path / "log"), "--ubx", str(out_ubx), "--rtcm", str(out_rtcm)]) == 0
    got_ubx, want_ubx = _ubx_identities(out_ubx), _ubx_identities(src_ubx)
    assert got_ubx == want_ubx and got_ubx["RXM-RAWX"] >= 10 and got_ubx["RXM-SFRBX"] > 0
    got_rtcm = _rtcm_identities(out_rtcm)
    assert got_rtcm == _rtcm_identities(src_rtcm)
    assert sum(v for k, v in got_rtcm.items() if k in ("1077", "1087", "1097", "1117", "1127")) >= 20   # MSM7
    if shutil.which("convbin") is None:
        return
    obs_r, obs_b = tmp_path / "rover.obs", tmp_path / "base.obs"
    subprocess.run(["convbin", "-r", "ubx", "-o", str(obs_r), str(out_ubx)], check=True, capture_output=True,
                   timeout=60)
    subprocess.run(["convbin", "-r", "rtcm3", "-tr", *RTCM_DATE, "-o", str(obs_b), str(out_rtcm)], check=True,
                   capture_output=True, timeout=60)
    print(f"RAWX {got_ubx['RXM-RAWX']}, rover RINEX epochs {_rinex_epochs(obs_r)}; "
          f"RTCM {sum(got_rtcm.values())} messages, base RINEX epochs {_rinex_epochs(obs_b)}")
    # every RAWX epoch a RINEX epoch but the first (convbin starts at the second; measured 14 RAWX -> 13)
    assert _rinex_epochs(obs_r) >= got_ubx["RXM-RAWX"] - 1
    assert _rinex_epochs(obs_b) >= 5


def test_only_the_gps_ports_replies_make_the_ubx_stream(tmp_path, capsys):
    """A ground station's shell session (SERIAL_CONTROL_DEV_SHELL) on the same link: its replies
    are not the receiver's bytes."""
    ubx = UBX.read_bytes()[:20000]
    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    w = FieldLogWriter(tmp_path / "log", background_flush=False)
    t = 0

    def reply(dev, part):
        return bytes(mav.serial_control_encode(dev, m.SERIAL_CONTROL_FLAG_REPLY, 0, 0, len(part),
                                               list(part) + [0] * (70 - len(part))).pack(mav))
    for k, i in enumerate(range(0, len(ubx), 70)):
        t += 1000
        w.write("mavlink", reply(m.SERIAL_CONTROL_DEV_GPS1, ubx[i:i + 70]), t, t)
        if k % 10 == 0:
            w.write("mavlink", reply(m.SERIAL_CONTROL_DEV_SHELL, b"nsh> ls /fs/microsd\r\n\xb5\x62\x02\x15"), t, t)
    w.close()
    out = tmp_path / "rover.ubx"
    assert main(["export", str(tmp_path / "log"), "--ubx", str(out)]) == 0
    assert out.read_bytes() == ubx
    text = capsys.readouterr().out
    assert "of GPS1" in text and "replies of other devices skipped" in text
    assert main(["export", str(tmp_path / "log"), "--ubx", str(out), "--device", "GPS2"]) == 0
    assert out.read_bytes() == b""                               # nothing from GPS2 in this log


def test_logged_solutions_as_rtklib_pos(tmp_path):
    """--pos: the logged solutions in RTKLIB's format, the NED sigmas in sdn/sde/sdu; pos2kml reads it."""
    import math

    import numpy as np

    from companion.messages import NavSolution
    from companion.nav.earth import ecef_to_geodetic, geodetic_to_ecef
    from companion.log_records import encode_solution
    rng = np.random.default_rng(3)
    sols = []
    for k in range(30):
        r = geodetic_to_ecef(np.radians(34.4 + 2e-6 * k), np.radians(132.5 - 1e-6 * k), 60.0 + 0.05 * k)
        sig = rng.uniform(0.05, 2.0, 3)
        sols.append(NavSolution(1.379e9 + 0.2 * k, r, np.zeros(3), np.eye(3), sig, np.full(3, 0.05),
                                np.full(3, 0.01), "init" if k == 0 else "nav", reset_counter=1,
                                extras={"inject": True, "mode": "tight", "imu_count": k, "t_boot_us": k}))
    w = FieldLogWriter(tmp_path / "log", background_flush=False)
    for k, s in enumerate(sols):
        w.write("solution", encode_solution(s), 1000 * k, 1000 * k)
    w.close()
    pos = tmp_path / "fused.pos"
    assert main(["export", str(tmp_path / "log"), "--pos", str(pos)]) == 0
    rows = [ln.split() for ln in pos.read_text().splitlines() if not ln.startswith("%")]
    assert len(rows) == len(sols) - 1                                   # the 'init' one left out
    for row, s in zip(rows, sols[1:]):
        lat, lon, h = ecef_to_geodetic(s.r_e)
        assert float(row[2]) == pytest.approx(math.degrees(lat), abs=1e-9)
        assert float(row[3]) == pytest.approx(math.degrees(lon), abs=1e-9)
        assert float(row[4]) == pytest.approx(h, abs=1e-4) and row[5] == "5"
        n, e, d = s.sigma_r_n_m
        assert [float(x) for x in row[7:10]] == pytest.approx([n, e, d], abs=1e-4)       # sdn sde sdu
        assert max(abs(float(x)) for x in row[10:13]) <= 1e-3                            # no correlations
    if shutil.which("pos2kml") is None:
        return
    kml = tmp_path / "fused.kml"
    subprocess.run(["pos2kml", "-a", "-o", str(kml), str(pos)], check=True, capture_output=True, timeout=30)
    assert kml.read_text().count("<Point>") == len(rows)


def test_fix_state_gives_the_rtklib_quality():
    import numpy as np

    from companion.gnss.pos_format import pos_records_from_nav_solutions
    from companion.messages import NavSolution
    from companion.nav.earth import geodetic_to_ecef
    r = geodetic_to_ecef(np.radians(-35.36), np.radians(149.16), 584.0)
    recs = pos_records_from_nav_solutions(
        [NavSolution(1.0e9 + k, r, np.zeros(3), np.eye(3), np.array([0.01, 0.02, 0.03]), np.zeros(3), np.zeros(3),
                     "nav", fix_state=fs) for k, fs in enumerate(["fixed", "float", "none"])])
    assert [x.quality for x in recs] == [1, 2, 5]
    # the covariance is the NED one turned into ECEF: its trace is kept
    assert np.trace(recs[0].cov_e) == pytest.approx(0.01 ** 2 + 0.02 ** 2 + 0.03 ** 2, rel=1e-12)
