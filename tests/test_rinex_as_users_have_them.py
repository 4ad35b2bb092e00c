"""Observation files as users have them: joined end to end with an overlap (hourly files, a logger
restarted), with 0.0 written for a signal not tracked (RINEX: "missing observations are written
as 0.0 or blanks"), and RINEX 3.02's band 1 for BeiDou B1I.  Built from real files."""
from __future__ import annotations

import re

import numpy as np
import pytest

from companion.gnss.rinex_obs import read_rinex_obs, reading_notes
from tests._data import data_path

pytestmark = pytest.mark.real_data

D = data_path("rtklib-testdata-geonet-2005/rinex")
ROVER, BASE, NAV = D / "07590920.05o", D / "30400920.05o", D / "07590920.05n"
#: a RINEX 2 epoch line: yy mm dd hh mm ss.sssssss, flag 0 or 1
EPOCH_LINE = re.compile(r"^ [ \d]\d( [ \d]\d){4} [ \d]\d\.\d{7}  [01]")
OVERLAP = 20                                  # epochs the second part repeats (10 min at 30 s)


def _header_and_epochs(path):
    """(header lines, [epoch blocks]) of a RINEX 2 file: a block is an epoch line and its satellites'."""
    lines = path.read_text().splitlines()
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    blocks = []
    for ln in lines[end:]:
        if EPOCH_LINE.match(ln):
            blocks.append([ln])
        else:
            blocks[-1].append(ln)
    return lines[:end], blocks


def _joined(tmp_path):
    """The file's epochs, then its last OVERLAP epochs again (what a second file that started early
    brings), then one epoch moved back in the middle of the first part."""
    head, blocks = _header_and_epochs(ROVER)
    body = blocks + blocks[-OVERLAP:]
    body[40], body[41] = body[41], body[40]
    out = tmp_path / "joined.05o"
    out.write_text("\n".join(head + [ln for b in body for ln in b]) + "\n")
    return out


def test_a_joined_file_reads_as_the_file_once_in_time_order(tmp_path):
    h0, e0 = read_rinex_obs(ROVER)
    h1, e1 = read_rinex_obs(_joined(tmp_path))
    assert repr(e1) == repr(e0)                    # (NaN fields: a dataclass == would never hold)
    assert h1["skipped"]["repeated epoch"] == OVERLAP and h1["out_of_order_epochs"] == 2
    notes = reading_notes(h1)
    assert f"{OVERLAP} epochs repeating an earlier time tag dropped" in notes and "time order" in notes
    assert reading_notes(h0) == ""


def test_zero_is_a_missing_observation(tmp_path):
    """G07's L2 carrier written as 0.000 at the first epoch: absent from that epoch, as a blank is."""
    head, blocks = _header_and_epochs(ROVER)
    first = blocks[0]
    row = 1 + re.findall(r"G[ \d]\d", first[0][32:]).index("G 7")          # G07's line in the block
    ln = first[row]
    first[row] = ln[:32] + f"{0.0:14.3f}  " + ln[48:]                      # field 3 of L1 C1 L2 P2
    path = tmp_path / "zero.05o"
    path.write_text("\n".join(head + [x for b in blocks for x in b]) + "\n")
    _, epochs = read_rinex_obs(path)
    l2 = {o.sat: o for o in epochs[0].observations if o.signal.startswith("L2")}
    assert np.isfinite(l2["G07"].pseudorange_m) and np.isnan(l2["G07"].carrier_cycles)
    assert np.isfinite(l2["G08"].carrier_cycles)


def test_rtk_on_the_joined_file_says_what_it_did_and_solves_as_the_original(tmp_path, capsys):
    import json
    from companion.cli import main
    res = {}
    for name, rover in (("orig", ROVER), ("joined", _joined(tmp_path))):
        js = tmp_path / f"{name}.json"
        assert main(["gnss", "--rover", str(rover), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk",
                     "--json", str(js)]) == 0
        res[name] = json.loads(js.read_text())
    out = capsys.readouterr().out
    assert f"rover file: {OVERLAP} epochs repeating an earlier time tag dropped" in out
    assert res["joined"]["reading_notes"]["rover"].startswith(f"{OVERLAP} epochs") and not res["orig"]["reading_notes"]
    a, b = (np.array([s["r_e"] for s in res[k]["solutions"]]) for k in ("orig", "joined"))
    assert a.shape == b.shape == (120, 3) and np.array_equal(a, b)


def test_rinex_302_beidou_b1i_is_band_2_as_in_303(tmp_path):
    """RINEX 3.02 labels B1I 'C1I'/'L1I'; 3.03 moved it to band 2 ('C2I') and gave band 1 to B1C
    (another carrier).  The Septentrio rover's 3.04 file rewritten as 3.02 reads the same."""
    src = data_path("matrtklib-septentrio-static-2024") / "rover.crx.gz"
    lines = hatanaka_text(src).splitlines()
    assert lines[0].startswith("     3.04")
    lines[0] = lines[0].replace("3.04", "3.02", 1)
    for i, ln in enumerate(lines):
        if ln.startswith("C ") and ln[60:].strip() == "SYS / # / OBS TYPES":
            lines[i] = ln[:60].replace("2I", "1I") + ln[60:]
            assert " C1I L1I " in lines[i]
        if "END OF HEADER" in ln:
            break
    old = tmp_path / "rover302.rnx"
    old.write_text("\n".join(lines) + "\n")
    h302, e302 = read_rinex_obs(old, "C")
    h304, e304 = read_rinex_obs(src, "C")
    assert h302["obs_types"]["C"] == h304["obs_types"]["C"] and repr(e302) == repr(e304)
    assert {o.signal for e in e302 for o in e.observations} >= {"L2I", "L7I", "L6I"}


def test_rinex2_cycle_slip_records_are_stepped_over(tmp_path):
    """A RINEX 2 epoch flag 6 (cycle slip records) is laid out as an epoch: its satellites' lines
    are skipped with it, and the epochs after it read as before."""
    head, blocks = _header_and_epochs(ROVER)
    slip = [blocks[5][0][:28] + "6" + blocks[5][0][29:]] + blocks[5][1:]    # epoch 5 again, flagged 6
    path = tmp_path / "slips.05o"
    path.write_text("\n".join(head + [ln for b in blocks[:6] + [slip] + blocks[6:] for ln in b]) + "\n")
    h, epochs = read_rinex_obs(path)
    assert repr(epochs) == repr(read_rinex_obs(ROVER)[1]) and h["skipped"]["event"] == 4     # 3 in the file


def test_a_time_window_steps_over_the_epochs_outside_it():
    """A base file of hours for a rover of minutes: only the span asked for is parsed."""
    for path in (ROVER, data_path("matrtklib-septentrio-static-2024") / "base.crx.gz"):      # RINEX 2 and 3
        _, every = read_rinex_obs(path, "GECJ")
        t0, t1 = every[10].t_gps, every[29].t_gps
        h, part = read_rinex_obs(path, "GECJ", (t0, t1))
        assert repr(part) == repr(every[10:30]) and h["epochs_outside_window"] == len(every) - 20


def test_zeroed_carriers_cost_the_car_few_fixes(tmp_path):
    """10 % of the 5.3-km car's carrier phases (its first 120 epochs) written as 0.000: taken as
    measured they left no epoch fixed; as missing ones, most epochs still fix."""
    import random

    from companion.gnss.rinex import read_rinex_nav
    from companion.gnss.rtk_post import solve_rtk_epochs
    car = data_path("cssrlib-fujisawa-car-2021")
    hr, rover = read_rinex_obs(car / "rover.crx.gz", "GEJ")
    hb, base = read_rinex_obs(car / "base.crx.gz", "GEJ")
    ephs = read_rinex_nav(car / "nav.rnx.gz", "GEJ")
    base_xyz = (-3959400.631, 3385704.533, 3667523.111)
    head = hatanaka_text(car / "rover.crx.gz").splitlines()
    end = next(i for i, ln in enumerate(head) if "END OF HEADER" in ln) + 1
    rng = random.Random(1)
    lines, n_epochs = head[:end], 0
    for ln in head[end:]:
        if ln.startswith(">"):
            n_epochs += 1
            if n_epochs > 120:
                break
        elif n_epochs and ln[:1] in "GEJ":
            sys_ = ln[0]
            codes = hr["obs_types"][sys_]
            fields = [ln[3 + 16 * k:3 + 16 * k + 16] for k in range(len(codes))]
            for k, c in enumerate(codes):
                if c[0] == "L" and fields[k].strip() and rng.random() < 0.1:
                    fields[k] = f"{0.0:14.3f}  "
            ln = ln[:3] + "".join(fields)
        lines.append(ln)
    zeroed = tmp_path / "rover_zeroed.rnx"
    zeroed.write_text("\n".join(lines) + "\n")
    hz, rz = read_rinex_obs(zeroed, "GEJ")
    sols, _ = solve_rtk_epochs(hz, rz, hb, base, ephs, base_xyz=base_xyz)
    full, _ = solve_rtk_epochs(hr, rover[:120], hb, base, ephs, base_xyz=base_xyz)
    n_fix, n_full = sum(s.quality == 1 for s in sols), sum(s.quality == 1 for s in full)
    print(f"10 % of the carriers 0.000: {n_fix} of {len(sols)} epochs fixed (the file as it is: {n_full})")
    assert len(sols) == 120 and n_fix >= 100


def hatanaka_text(path) -> str:
    import hatanaka
    return hatanaka.decompress(path).decode("ascii")


def test_rinex2_glonass_observations_take_glonass_codes(tmp_path):
    """RINEX 2's P1/P2/L2 are GPS's W codes but GLONASS's P codes (RINEX 3 'C1P', 'L2P'): a
    GLONASS satellite of a mixed RINEX 2 file (G03 relabelled R03 here) keeps its L2 and P code."""
    head, blocks = _header_and_epochs(ROVER)
    for b in blocks:
        b[0] = b[0][:32] + b[0][32:].replace("G 3", "R 3")
    path = tmp_path / "mixed.05o"
    path.write_text("\n".join(head + [ln for b in blocks for ln in b]) + "\n")
    _, epochs = read_rinex_obs(path, "GR")
    sig = {(o.sat[0], o.signal) for o in epochs[0].observations}
    assert {("R", "L1C"), ("R", "L2P"), ("G", "L1C"), ("G", "L2W")} <= sig and ("R", "L2W") not in sig


@pytest.mark.parametrize("mode", ["rtk", "dgps"])
def test_a_base_or_nav_of_another_day_is_said_with_both_spans(mode, capsys):
    """The 2021 car's base for the 2005 GEONET rover, the 2005 nav for the 2021 car: each error
    names what the files cover, not an empty solution."""
    from companion.cli import main
    car = data_path("cssrlib-fujisawa-car-2021")
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(car / "base.crx.gz"),
                 "--mode", mode]) == 2
    err = capsys.readouterr().err
    assert ("the base file has no epochs during the rover's (2005/04/02 00:00:00 to 00:59:30 GPST): it covers "
            "2021/09/22 06:30:00 to 06:35:59 GPST") in err
    assert main(["gnss", "--rover", str(car / "rover.crx.gz"), "--nav", str(NAV), "--base", str(car / "base.crx.gz"),
                 "--mode", mode]) == 2
    err = capsys.readouterr().err
    assert "(2021/09/22 06:30:00 to 06:35:59 GPST); the navigation file(s) are of 2005/04/01" in err


def test_a_file_cut_mid_epoch_or_a_corrupt_line_costs_one_epoch(tmp_path):
    """A field log cut while writing (RINEX 3, the car's rover cut halfway through an epoch) and a
    corrupt line in a RINEX 2 epoch: the epoch is counted unreadable, every other one is read."""
    car = data_path("cssrlib-fujisawa-car-2021") / "rover.crx.gz"
    text = hatanaka_text(car)
    cut = text.index(">", len(text) // 2) + 200                  # inside an epoch's satellite lines
    path = tmp_path / "cut.rnx"
    path.write_text(text[:cut])
    _, car_every = read_rinex_obs(car, "GEJ")
    h, part = read_rinex_obs(path, "GEJ")
    assert h["skipped"]["unreadable epoch"] == 1 and repr(part) == repr(car_every[:len(part)])
    assert len(part) == text[:cut].count("\n>") - 1
    assert reading_notes(h) == "1 epoch unreadable (a file cut mid-epoch or a corrupt line) skipped"

    head, blocks = _header_and_epochs(ROVER)
    blocks[7][0] = blocks[7][0][:10] + "xx" + blocks[7][0][12:]          # the hour of epoch 7's line
    path = tmp_path / "corrupt.05o"
    path.write_text("\n".join(head + [ln for b in blocks for ln in b]) + "\n")
    h, eps = read_rinex_obs(path)
    _, every = read_rinex_obs(ROVER)
    assert h["skipped"]["unreadable epoch"] == 1 and repr(eps) == repr(every[:7] + every[8:])

    lines = text.splitlines()                                   # RINEX 3: one satellite's line corrupt
    k = next(i for i, ln in enumerate(lines) if ln.startswith("G") and i > 400)
    sat, lines[k] = lines[k][:3], "garbage !!" + lines[k][10:]
    path = tmp_path / "corrupt.rnx"
    path.write_text("\n".join(lines) + "\n")
    h, eps = read_rinex_obs(path, "GEJ")
    assert h["skipped"]["unreadable satellite line"] == 1 and len(eps) == len(car_every)
    assert "1 satellite line unreadable (a corrupt line) skipped" in reading_notes(h)
    assert sum(o.sat == sat for e in eps for o in e.observations) < sum(o.sat == sat for e in car_every
                                                                      for o in e.observations)


def test_a_navigation_file_given_as_observations_is_said_so():
    with pytest.raises(ValueError, match="not a RINEX observation file .*'N: GPS NAV DATA': a navigation file"):
        read_rinex_obs(NAV)


def test_a_navigation_file_cut_mid_record_or_with_a_corrupt_line_loses_that_record(tmp_path, capsys):
    """RINEX 2 (GEONET) and RINEX 3 (the car's mixed nav): the record cut or corrupted is left out
    and counted, every other one is read; `companion gnss` says so."""
    from companion.cli import main
    from companion.gnss.rinex import read_rinex_nav
    text = NAV.read_text()
    whole = read_rinex_nav(NAV, "G")
    cut = tmp_path / "cut.05n"
    cut.write_text(text[:len(text) // 2 + 37])             # mid-record (a record is 8 lines of ~80)
    counts: dict = {}
    part = read_rinex_nav(cut, "G", counts)
    assert counts["unreadable records"] == 1 and len(part) == len(whole) // 2 - 1
    assert all(a.t_oe_gps == b.t_oe_gps and a.sqrt_a == b.sqrt_a for a, b in zip(part, whole))

    car = data_path("cssrlib-fujisawa-car-2021")
    lines = hatanaka_text(car / "nav.rnx.gz").splitlines()
    whole = read_rinex_nav(car / "nav.rnx.gz", "GEJ")
    k = next(i for i, ln in enumerate(lines) if ln.startswith("G") and i > 100) + 3     # (a Galileo I/NAV has an F/NAV twin)
    lines[k] = "garbage !!"
    bad = tmp_path / "bad.rnx"
    bad.write_text("\n".join(lines) + "\n")
    counts = {}
    assert len(read_rinex_nav(bad, "GEJ", counts)) == len(whole) - 1 and counts["unreadable records"] == 1
    assert main(["gnss", "--rover", str(car / "rover.crx.gz"), "--nav", str(bad), "--sys", "G,E,J"]) == 0
    assert "bad.rnx: 1 record unreadable (a file cut mid-record or a corrupt line) skipped" in capsys.readouterr().out


def _split_rinex3(src, tmp_path, parts: int, stem: str = "base") -> list:
    """A RINEX 3 file cut into ``parts`` files of consecutive epochs, each with the header (a
    CORS's hourly files), written last part first."""
    text = hatanaka_text(src)
    head, _, body = text.partition("END OF HEADER")
    head += "END OF HEADER" + body[:body.index("\n") + 1]
    epochs = [">" + e for e in body[body.index("\n") + 1:].split("\n>")]
    epochs[0] = epochs[0][1:]
    size = -(-len(epochs) // parts)
    out = []
    for k in reversed(range(parts)):
        p = tmp_path / f"{stem}_part{k}.rnx"
        p.write_text(head + "\n".join(epochs[k * size:(k + 1) * size]) + "\n")
        out.append(p)
    return out


def test_several_base_files_of_one_station_are_one_base(tmp_path, capsys):
    """The Septentrio base cut in three (given last first): the same RTK solutions as the whole
    file; files of two stations, or a capture among files, are refused."""
    import json
    from companion.cli import main
    sep = data_path("matrtklib-septentrio-static-2024")
    parts = _split_rinex3(sep / "base.crx.gz", tmp_path, 3)
    res = {}
    for name, base in (("whole", [sep / "base.crx.gz"]), ("parts", parts)):
        js = tmp_path / f"{name}.json"
        assert main(["gnss", "--rover", str(sep / "rover.crx.gz"), "--nav", str(sep / "base.nav.gz"), "--mode", "rtk",
                     "--base", *map(str, base), "--base-xyz=-3817681.121326613,3562839.431140291,3650159.1593410783",
                     "--json", str(js)]) == 0
        res[name] = json.loads(js.read_text())
    assert res["parts"]["base_epochs"] == res["whole"]["base_epochs"] == 120
    assert [s["r_e"] for s in res["parts"]["solutions"]] == [s["r_e"] for s in res["whole"]["solutions"]]
    capsys.readouterr()
    car = data_path("cssrlib-fujisawa-car-2021")
    assert main(["gnss", "--rover", str(car / "rover.crx.gz"), "--nav", str(car / "nav.rnx.gz"), "--mode", "rtk",
                 "--base", str(car / "base.crx.gz"), str(parts[0])]) == 2
    assert "is not of the station of" in capsys.readouterr().err
    capture = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"
    assert main(["gnss", "--rover", str(car / "rover.crx.gz"), "--nav", str(car / "nav.rnx.gz"), "--mode", "dgps",
                 "--base", str(car / "base.crx.gz"), str(capture)]) == 2
    assert "a u-blox or RTCM capture is given alone" in capsys.readouterr().err


def test_several_rover_files_of_one_receiver_are_one_rover(tmp_path, capsys):
    """The moving car's rover file cut in three (given last first, as a shell's glob may not):
    the same RTK and SPP solutions as the whole file, its name in the titles; files of another
    receiver (its type, or its serial number for two of one model) are refused, not read as the
    rover jumping between them."""
    import json
    from companion.cli import main
    car = data_path("cssrlib-fujisawa-car-2021")
    parts = _split_rinex3(car / "rover.crx.gz", tmp_path, 3, stem="rover")
    common = ["--nav", str(car / "nav.rnx.gz"), "--base", str(car / "base.crx.gz")]
    res = {}
    for mode in ("rtk", "spp"):
        for name, rover in (("whole", [car / "rover.crx.gz"]), ("parts", parts)):
            js = tmp_path / f"{mode}_{name}.json"
            assert main(["gnss", "--rover", *map(str, rover), *common, "--mode", mode, "--json", str(js),
                         "--kml", str(tmp_path / f"{mode}_{name}.kml")]) == 0
            res[mode, name] = json.loads(js.read_text())
        whole, cut = res[mode, "whole"], res[mode, "parts"]
        assert cut["epochs"] == whole["epochs"] == 360
        assert [s["r_e"] for s in cut["solutions"]] == [s["r_e"] for s in whole["solutions"]]
    assert res["rtk", "parts"]["fixed"] >= 350
    assert "rover_part2.rnx and 2 more" in (tmp_path / "rtk_parts.kml").read_text()
    capsys.readouterr()
    assert main(["gnss", "--rover", str(parts[0]), str(car / "base.crx.gz"), *common, "--mode", "rtk"]) == 2
    assert "is not of the receiver of" in capsys.readouterr().err
    sep = data_path("matrtklib-septentrio-static-2024")     # two mosaic-X5s: only the serials differ
    assert main(["gnss", "--rover", str(sep / "rover.crx.gz"), str(sep / "base.crx.gz"), "--nav",
                 str(sep / "base.nav.gz"), "--base", str(sep / "base.crx.gz"), "--mode", "rtk"]) == 2
    assert "receiver number '3605054', not '3604480'" in capsys.readouterr().err
    raised = tmp_path / "raised.rnx"           # the antenna lifted between two files: one offset cannot serve both
    raised.write_text(re.sub(r".*ANTENNA: DELTA H/E/N", f"{1.5:14.4f}{0:14.4f}{0:14.4f}" + " " * 18
                             + "ANTENNA: DELTA H/E/N", parts[1].read_text(), count=1))
    assert main(["gnss", "--rover", str(parts[0]), str(raised), *common, "--mode", "rtk"]) == 2
    assert "has another antenna offset (ANTENNA: DELTA H/E/N)" in capsys.readouterr().err


def _in_utc(text: str, system: str, leap_s: int, keep_leap_line: bool) -> str:
    """A RINEX 3 file in GPS time rewritten with its time tags in UTC and ``system`` ('GLO': what
    RINEX calls GLONASS's UTC) in TIME OF FIRST OBS; the LEAP SECONDS line kept or dropped."""
    import datetime as dt

    def back(m):
        t = dt.datetime(*map(int, m.group(1).split()), int(float(m.group(2)))) - dt.timedelta(seconds=leap_s)
        return f"> {t:%Y %m %d %H %M} {t.second:2d}.0000000"
    head, _, body = text.partition("END OF HEADER")
    head = "\n".join(ln[:48] + f"{system:<3}" + ln[51:] if "TIME OF FIRST OBS" in ln else ln
                     for ln in head.split("\n") if keep_leap_line or "LEAP SECONDS" not in ln)
    body = re.sub(r"^> (\d{4} \d\d \d\d \d\d \d\d) +(\d+\.\d{7})", back, body, flags=re.M)
    return head + "END OF HEADER" + body


@pytest.mark.parametrize("system,keep_leap_line", [("GLO", True), ("UTC", False)])
def test_time_tags_in_utc_are_moved_to_gps_time(system, keep_leap_line, tmp_path):
    """A file whose TIME OF FIRST OBS says GLO (GLONASS's UTC) or UTC: its tags are GPS time less
    the leap seconds (the header's LEAP SECONDS, else the table's).  Before, they were taken as GPS
    time, 18 s off: every satellite 18 s off in its orbit, kilometres."""
    sep = data_path("matrtklib-septentrio-static-2024")
    _, gps = read_rinex_obs(sep / "rover.crx.gz", "GEJ")
    p = tmp_path / "utc.rnx"
    p.write_text(_in_utc(hatanaka_text(sep / "rover.crx.gz"), system, 18, keep_leap_line))
    hdr, utc = read_rinex_obs(p, "GEJ")
    assert hdr["time_system"] == system and hdr["time_tag_to_gps_s"] == 18.0
    assert [e.t_gps for e in utc] == [e.t_gps for e in gps] and len(utc) == 120
    assert f"time tags in {system} (UTC) moved to GPS time (+18 s)" in reading_notes(hdr)


def test_a_glonass_only_file_without_a_time_system_is_in_utc(tmp_path):
    """RINEX 2.11: a pure GLONASS file may leave the time system blank, and is then in UTC (GLO).
    GEONET's file relabelled GLONASS-only: its tags move by 2005's 13 leap seconds."""
    lines = ROVER.read_text().splitlines()
    lines[0] = lines[0][:40] + "R (GLONASS)".ljust(20) + lines[0][60:]
    lines = [ln[:48] + "   " + ln[51:] if "TIME OF FIRST OBS" in ln else ln for ln in lines]
    p = tmp_path / "glonass_only.05o"
    p.write_text("\n".join(lines) + "\n")
    _, gps = read_rinex_obs(ROVER, "G")
    hdr, utc = read_rinex_obs(p, "G")
    assert hdr["time_system"] == "GLO"
    assert [e.t_gps for e in utc] == [e.t_gps + 13.0 for e in gps]
