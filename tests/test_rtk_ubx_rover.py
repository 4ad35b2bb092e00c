"""``companion gnss --mode rtk`` with a u-blox capture as the rover (RXM-RAWX, decoded as the
service decodes its receiver), the way an F9P user logs it.

The capture is made here from the real Septentrio rover of tests/data/matrtklib-septentrio-static-2024:
each epoch's observations of the signals an F9 tracks (GPS L1 C/A + L2C, Galileo E1 + E5a + E5b,
BeiDou B1I + B2I + B3I, QZSS L1 C/A + L2C + L5; not GPS L2 P(Y)) packed into RXM-RAWX by pyubx2,
the lock time counted from the first epoch and restarted at each loss-of-lock flag.  The same
observations from the RINEX file must give the same solutions."""
from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest

from companion.gnss.rinex_obs import read_rinex_obs
from tests.test_rtk_septentrio_static import BASE, BASE_XYZ, NAV, REF_ROVER, ROVER

pyubx2 = pytest.importorskip("pyubx2", reason="pip install 'companion[receiver]'")

pytestmark = pytest.mark.real_data

#: RINEX 3 code -> (gnssId, sigId) of RXM-RAWX (u-blox F9 interface description)
UBX_SIGNAL = {("G", "L1C"): (0, 0), ("G", "L2L"): (0, 3), ("E", "L1C"): (2, 0), ("E", "L5Q"): (2, 4),
              ("E", "L7Q"): (2, 6), ("C", "L2I"): (3, 0), ("C", "L7I"): (3, 2), ("C", "L6I"): (3, 4),
              ("J", "L1C"): (5, 0), ("J", "L2L"): (5, 5), ("J", "L5Q"): (5, 9)}
WEEK_S = 604800.0


def _rawx_capture(path) -> set[tuple[str, str]]:
    """The rover RINEX as RXM-RAWX frames in ``path``; returns the (system, code) pairs written.
    The payload is packed here by the interface description's layout and framed by pyubx2
    (pyubx2's keyword construction of 70 repeated groups takes 0.5 s a message); pyubx2 parses
    the first frame back as a check of the layout."""
    from pyubx2 import GET, UBXMessage, UBXReader
    _, epochs = read_rinex_obs(ROVER, "GECJ")
    lock_start: dict = {}
    written = set()
    first = None
    with open(path, "wb") as fh:
        for e in epochs:
            meas = []
            for o in e.observations:
                ids = UBX_SIGNAL.get((o.sat[0], o.signal))
                if ids is None or not (math.isfinite(o.pseudorange_m) and math.isfinite(o.carrier_cycles)):
                    continue
                key = (o.sat, o.signal)
                if key not in lock_start or o.loss_of_lock:
                    lock_start[key] = e.t_gps
                lock_ms = min(64500, int(round((e.t_gps - lock_start[key]) * 1000.0)))
                trk = 0x03 | (0 if o.half_cycle_ambiguous else 0x04)       # prValid, cpValid, halfCyc
                meas.append(struct.pack("<ddfBBBBHBBBBBx", o.pseudorange_m, o.carrier_cycles,
                                        o.doppler_hz if math.isfinite(o.doppler_hz) else 0.0, ids[0], int(o.sat[1:]),
                                        ids[1], 0, lock_ms, int(o.cn0_dbhz) if math.isfinite(o.cn0_dbhz) else 40,
                                        2, 1, 3, trk))
                written.add((o.sat[0], o.signal))
            head = struct.pack("<dHbBBB2x", e.t_gps % WEEK_S, int(e.t_gps // WEEK_S), 18, len(meas), 0x01, 1)
            frame = UBXMessage("RXM", "RXM-RAWX", GET, payload=head + b"".join(meas)).serialize()
            first = first or (frame, e, len(meas))
            fh.write(frame)
    frame, e, n = first
    m = UBXReader.parse(frame)
    assert m.numMeas == n and m.week == int(e.t_gps // WEEK_S) and abs(m.rcvTow - e.t_gps % WEEK_S) < 1e-9
    assert m.prValid_01 == 1 and m.cpValid_01 == 1
    return written


def test_a_ubx_rover_gives_the_solutions_of_the_same_observations_in_rinex(tmp_path):
    from companion.cli import main
    ubx = tmp_path / "rover.ubx"
    written = _rawx_capture(ubx)
    assert {s for s, _ in written} == set("GECJ") and ("G", "L2L") in written
    xyz = ",".join(f"{v}" for v in BASE_XYZ)
    out = {}
    for name, rover in (("ubx", ubx), ("rinex", ROVER)):
        js = tmp_path / f"{name}.json"
        assert main(["gnss", "--rover", str(rover), "--base", str(BASE), "--nav", str(NAV), "--base-xyz=" + xyz,
                     "--mode", "rtk", "--json", str(js)]) == 0
        out[name] = json.loads(js.read_text())
    u, r = out["ubx"]["solutions"], out["rinex"]["solutions"]
    assert len(u) == len(r) == 120 and all(s["q"] == 1 for s in u)
    # the capture has no GPS L2 P(Y): fewer fixed DD ambiguities than the RINEX run, the same place
    assert np.mean([s["n_fixed"] for s in u]) < np.mean([s["n_fixed"] for s in r])
    ru = np.array([s["r_e"] for s in u])
    rms = float(np.sqrt(np.mean(np.sum((ru - REF_ROVER) ** 2, axis=1))))
    d = np.linalg.norm(ru - np.array([s["r_e"] for s in r]), axis=1)
    print(f"u-blox rover: 120/120 fixed, RMS 3-D {rms:.4f} m from the reference; at most {d.max():.4f} m "
          f"from the RINEX run with P(Y)")
    assert rms < 0.004 and d.max() < 0.01


def test_one_system_of_a_capture_and_a_capture_without_ephemerides(tmp_path, capsys):
    from companion.cli import main
    ubx = tmp_path / "rover.ubx"
    _rawx_capture(ubx)
    xyz = "--base-xyz=" + ",".join(f"{v}" for v in BASE_XYZ)
    assert main(["gnss", "--rover", str(ubx), "--base", str(BASE), "--nav", str(NAV), "--mode", "rtk",
                 "--sys", "G", xyz]) == 0
    out = capsys.readouterr().out
    assert "120/120 epochs solved, 120 fixed" in out and "G 9.0 (9-9)" in out and "E " not in out.split("satellites")[-1]
    # no --nav and no RXM-SFRBX in this capture: said so
    assert main(["gnss", "--rover", str(ubx), "--base", str(BASE), "--mode", "rtk", xyz]) == 2
    assert "neither capture brings them" in capsys.readouterr().err
