"""Receiver antenna calibrations: where each carrier's phase centre is (an offset from the antenna
reference point, ARP, and a variation with the satellite's direction), read from an IGS ANTEX file
(``igs20.atx``) or an NGS ``ant_info`` file (``ngs_abs.pcv``), as RTKLIB's ``file-rcvantfile``.

Why: a RINEX base position is its ARP, but the phase is measured at the phase centre, centimetres
above it (a choke ring's L1 centre is 11 cm up, its L2 centre 13 cm).  Left out, the rover's
height carries the difference between the two antennas' offsets (and L1 and L2 disagree by it);
between two antennas of one type it cancels.

The range to a satellite in direction ``u`` (unit, east/north/up) from the ARP is corrected as
RTKLIB's ``antmodel`` does: ``-(PCO . u) + PCV(zenith, azimuth)``, added to the modelled range of
the carrier's phase and code.  A frequency the calibration lacks takes the one of GPS nearest to
it (an L5 or E5a from L2 when a calibration has only L1/L2, as the IGS conventions do); every
such substitution is listed in :attr:`AntennaCalibration.notes`.

Antenna types are IGS names: a model of up to 16 characters and a radome (blank = ``NONE``); a
radome that is not calibrated falls back to the model without one, and says so.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .glonass import carrier_hz as glonass_carrier_hz
from .signals import FREQUENCY_HZ, GLONASS


@dataclass(frozen=True)
class FrequencyCalibration:
    """One frequency's phase centre: offset and variations (both m)."""
    pco_enu_m: np.ndarray                 # offset of the mean phase centre from the ARP: east, north, up
    zenith_deg: np.ndarray                # the PCV grid's zenith angles
    pcv_noazi_m: np.ndarray               # azimuth-independent variation at each zenith angle
    azimuth_deg: np.ndarray | None = None  # the grid's azimuths (0..360), when the file gives them
    pcv_m: np.ndarray | None = None        # (azimuth, zenith) variation

    def range_offset_m(self, u_enu: np.ndarray) -> float:
        """What the modelled range from the ARP gains for this carrier (RTKLIB's ``antmodel``)."""
        up = min(max(float(u_enu[2]), -1.0), 1.0)
        zen = math.degrees(math.acos(up))
        if self.pcv_m is not None:
            # bilinear: the two azimuth rows around the satellite's, each at its zenith angle
            az = math.degrees(math.atan2(float(u_enu[0]), float(u_enu[1]))) % 360.0
            k = min(max(int(np.searchsorted(self.azimuth_deg, az, side="right")) - 1, 0), len(self.azimuth_deg) - 2)
            a0, a1 = self.azimuth_deg[k], self.azimuth_deg[k + 1]
            w = min(max((az - a0) / (a1 - a0), 0.0), 1.0)
            pcv = float((1.0 - w) * np.interp(zen, self.zenith_deg, self.pcv_m[k])
                        + w * np.interp(zen, self.zenith_deg, self.pcv_m[k + 1]))
        else:
            pcv = float(np.interp(zen, self.zenith_deg, self.pcv_noazi_m))
        return -float(self.pco_enu_m @ u_enu) + pcv


@dataclass
class AntennaCalibration:
    """One antenna type's calibration: frequency code (ANTEX's 'G01', 'E05', ...) -> its values."""
    name: str                             # 'TRM59800.00     SCIS' (model, radome) as the file has it
    source: str                           # the file it came from
    frequencies: dict[str, FrequencyCalibration]
    notes: list[str] = field(default_factory=list)
    entry: str = ""                       # the file's own type text (what RTKLIB is given to find it)

    def __post_init__(self):
        self._own = tuple(self.frequencies)   # the file's frequencies (substitutes come from these only)

    def frequency(self, system: str, band: str) -> FrequencyCalibration:
        """The calibration of ``band`` ('1', '2', '5' ...) of ``system``, or of GPS's frequency
        nearest to it (noted once) when the file has none of its own (any frequency of the file
        when it has no GPS one, its first when the band's frequency is unknown)."""
        code = f"{system}{band:0>2}"
        cal = self.frequencies.get(code)
        if cal is not None:
            return cal
        f = _carrier_hz(system, band)
        have = [c for c in self._own if c[0] == "G"] or list(self._own)
        use = min(have, key=lambda c: abs(_carrier_hz(c[0], c[1:].lstrip("0")) - f)) if math.isfinite(f) else have[0]
        self.frequencies[code] = self.frequencies[use]
        self.notes.append(f"{code} from {use}")
        return self.frequencies[use]

    def range_offset_m(self, system: str, band: str, u_enu: np.ndarray) -> float:
        return self.frequency(system, band).range_offset_m(u_enu)


def _carrier_hz(system: str, band: str) -> float:
    """A band's carrier frequency (GLONASS: channel 0's), NaN when unknown."""
    if system == GLONASS:
        return glonass_carrier_hz(f"L{band}C", 0)
    return FREQUENCY_HZ.get(system, {}).get(band, float("nan"))


def antenna_key(name: str) -> tuple[str, str]:
    """(model, radome) of an IGS antenna name as typed ('TRM59800.00 SCIS', 'TRM29659.00',
    'LEIAR25.R4 NONE')."""
    words = name.split()
    if not words:
        return "", "NONE"
    return words[0].upper(), (words[1].upper() if len(words) > 1 else "NONE")


def _keys(name: str) -> list[tuple[str, str]]:
    """The (model, radome) ``name`` can mean: as typed, and as a RINEX header's 20 columns (model
    in 16, radome in 4: 'Tallysman TW7972NONE' is the model 'Tallysman TW7972' without a radome)."""
    keys = [antenna_key(name)]
    if len(name) > 16:
        cols = (name[:16].strip().upper(), name[16:20].strip().upper() or "NONE")
        if cols not in keys:
            keys.append(cols)
    return keys


def read_antenna_file(path) -> dict[tuple[str, str], AntennaCalibration]:
    """(model, radome) -> calibration of every receiver antenna in an ANTEX or NGS ``ant_info`` file."""
    text = Path(path).read_text(encoding="latin-1")
    lines = text.splitlines()
    if any(ln[60:80].strip() == "ANTEX VERSION / SYST" for ln in lines[:5]):
        out = _read_antex(lines, str(path))
    else:
        out = _read_ngs(lines, str(path))
    if not out:
        raise ValueError(f"{path}: no receiver antenna calibration in it (an ANTEX or NGS ant_info file expected)")
    return out


def find_antenna(cals: dict[tuple[str, str], AntennaCalibration], name: str) -> AntennaCalibration | None:
    """``name``'s calibration (a copy: its frequency substitutions are its own), the radome-less
    one of its model when its radome is not in the file (noted), or None."""
    keys = _keys(name)
    cal = next((cals[k] for k in keys if k in cals), None)
    notes = []
    for model, radome in keys:
        if cal is None and radome != "NONE" and (model, "NONE") in cals:
            cal = cals[(model, "NONE")]
            notes.append(f"radome {radome} not calibrated: {model} without one used")
    if cal is None:
        return None
    return AntennaCalibration(cal.name, cal.source, dict(cal.frequencies), notes, cal.entry)


def receiver_antenna(cals: dict, asked: str | None, header: str | None, who: str, path: str) \
        -> tuple[AntennaCalibration | None, dict]:
    """(calibration or None, the JSON's account of it) of the ``who`` ('rover', 'base') receiver:
    the type ``asked`` (an error when the file lacks it), else its RINEX header's (the phase centre
    stays at the ARP, said, when the file lacks it or the header names none)."""
    name = asked or header or ""
    info = {"type": name or None, "from": "asked" if asked else "header", "calibration": None, "notes": []}
    cal = find_antenna(cals, name) if name.strip() and name.strip().upper() != "UNKNOWN" else None
    if cal is None:
        if asked:
            raise ValueError(f"the {who} antenna {asked!r} is not in {path}")
        why = "no antenna type in the header" if not name.strip() else "not in the file"
        info["notes"].append(f"{why}: phase centres taken at the ARP")
        return None, info
    info["calibration"] = f"{Path(path).name}: {cal.name}"
    info["entry"] = cal.entry
    info["notes"] = cal.notes              # the same list: the frequencies it substitutes are added as used
    return cal, info


def _floats(s: str) -> list[float]:
    return [float(v) for v in s.split()]


def _enu(north_east_up_mm) -> np.ndarray:
    n, e, u = north_east_up_mm
    return np.array([e, n, u]) * 1e-3


def _read_antex(lines: list[str], source: str) -> dict:
    """Receiver antennas of an ANTEX 1.3/1.4 file (satellite antennas, which name an SVN, are skipped;
    a type's mean calibration is preferred to an individual antenna's)."""
    out: dict[tuple[str, str], AntennaCalibration] = {}
    individual: set = set()
    ant = freq = None
    in_rms = False
    for ln in lines:
        label = ln[60:80].strip()
        if label == "START OF ANTENNA":
            ant = {"freqs": {}, "zen": None, "dazi": 0.0}
        elif ant is None:
            continue
        elif label == "TYPE / SERIAL NO":
            ant["key"] = (ln[0:16].strip().upper(), ln[16:20].strip().upper() or "NONE")
            ant["entry"] = ln[0:20].rstrip()
            ant["serial"] = ln[20:40].strip()
            ant["satellite"] = bool(ln[40:50].strip())
        elif label == "DAZI":
            ant["dazi"] = float(ln[2:8])
        elif label == "ZEN1 / ZEN2 / DZEN":
            z1, z2, dz = float(ln[2:8]), float(ln[8:14]), float(ln[14:20])
            ant["zen"] = np.arange(z1, z2 + 0.5 * dz, dz)
        elif label == "START OF FREQ RMS":
            in_rms = True
        elif label == "END OF FREQ RMS":
            in_rms = False
        elif label == "START OF FREQUENCY" and not in_rms:
            freq = {"code": ln[3:6].strip(), "pco": None, "noazi": None, "rows": []}
        elif label == "NORTH / EAST / UP" and freq is not None and not in_rms:
            freq["pco"] = _enu([float(ln[0:10]), float(ln[10:20]), float(ln[20:30])])
        elif label == "END OF FREQUENCY" and freq is not None:
            ant["freqs"][freq["code"]] = _antex_frequency(freq, ant)
            freq = None
        elif label == "END OF ANTENNA":
            key = ant.get("key")
            if key and not ant.get("satellite") and ant["freqs"]:
                mean = not ant.get("serial")
                if key not in out or (mean and key in individual):
                    out[key] = AntennaCalibration(f"{key[0]:<16}{key[1]}", source, ant["freqs"], entry=ant["entry"])
                    (individual.discard if mean else individual.add)(key)
            ant = None
        elif freq is not None and not in_rms and ant["zen"] is not None:
            if ln[3:8] == "NOAZI":
                freq["noazi"] = np.array(_floats(ln[8:])) * 1e-3
            elif ln.strip():
                freq["rows"].append((float(ln[0:8]), np.array(_floats(ln[8:])) * 1e-3))
    return out


def _antex_frequency(freq: dict, ant: dict) -> FrequencyCalibration:
    zen = ant["zen"]
    noazi = freq["noazi"] if freq["noazi"] is not None else np.zeros(len(zen))
    if len(noazi) != len(zen) or freq["pco"] is None:
        raise ValueError(f"ANTEX {ant.get('key')} {freq['code']}: {len(noazi)} values for {len(zen)} zenith angles"
                         if freq["pco"] is not None else f"ANTEX {ant.get('key')} {freq['code']}: no NORTH / EAST / UP")
    rows = freq["rows"]
    if ant["dazi"] > 0 and len(rows) >= 2 and all(len(v) == len(zen) for _, v in rows):
        return FrequencyCalibration(freq["pco"], zen, noazi, np.array([a for a, _ in rows]),
                                    np.array([v for _, v in rows]))
    return FrequencyCalibration(freq["pco"], zen, noazi)


#: an NGS ant_info entry after its name line: L1 offset (N, E, U), PCV at elevations 90..45 and
#: 40..0 by 5 degrees, then the same for L2 (mm)
_NGS_COUNTS = (3, 10, 9, 3, 10, 9)


def _read_ngs(lines: list[str], source: str) -> dict:
    out: dict[tuple[str, str], AntennaCalibration] = {}
    zenith = np.arange(0.0, 90.1, 5.0)            # elevation 90 .. 0
    k = 0
    while k < len(lines):
        ln = lines[k]
        if ln[:1].strip() and len(lines) > k + 6:
            try:
                vals = [_floats(lines[k + 1 + i]) for i in range(6)]
            except ValueError:
                vals = []
            if [len(v) for v in vals] == list(_NGS_COUNTS):
                key = (ln[0:16].strip().upper(), ln[16:20].strip().upper() or "NONE")
                freqs = {code: FrequencyCalibration(_enu(vals[i]), zenith, np.array(vals[i + 1] + vals[i + 2]) * 1e-3)
                         for code, i in (("G01", 0), ("G02", 3))}
                out.setdefault(key, AntennaCalibration(f"{key[0]:<16}{key[1]}", source, freqs, entry=ln[0:20].rstrip()))
                k += 7
                continue
        k += 1
    return out


def _sky_directions() -> np.ndarray:
    """Unit ENU vectors over the sky above 5 degrees: 8 azimuths x 9 elevations, and the zenith."""
    out = [np.array([0.0, 0.0, 1.0])]
    for el in np.radians(np.arange(5.0, 90.0, 10.0)):
        for az in np.radians(np.arange(0.0, 360.0, 45.0)):
            out.append(np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)]))
    return np.array(out)


_SKY = _sky_directions()


def largest_change_m(before: AntennaCalibration | None, after: AntennaCalibration | None,
                     bands_by_system: dict[str, str] | None = None) -> float:
    """The most a receiver's modelled range changes from one calibration to the other (None: the
    phase centre taken at the ARP) over the sky and the bands each system is used on
    (``bands_by_system``, e.g. ``{'G': '12', 'E': '15'}``; GPS L1/L2 when not given): what a
    position solved from its observables can move by when it changes."""
    worst = 0.0
    for system, bands in (bands_by_system or {"G": "12"}).items():
        for band in bands:
            for u in _SKY:
                a = before.range_offset_m(system, band, u) if before is not None else 0.0
                b = after.range_offset_m(system, band, u) if after is not None else 0.0
                worst = max(worst, abs(b - a))
    return worst


__all__ = ["AntennaCalibration", "FrequencyCalibration", "antenna_key", "find_antenna", "largest_change_m",
           "read_antenna_file", "receiver_antenna"]
