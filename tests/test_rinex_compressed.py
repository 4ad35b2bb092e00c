"""Compressed RINEX (issue 11): Hatanaka (.crx / .YYd), gzip and both together read exactly as the
plain file, through the hatanaka package's RNXCMP; an unknown format is a clear error."""
from __future__ import annotations

import numpy as np
import pytest

from companion.gnss.rinex import read_rinex_nav
from companion.gnss.rinex_obs import read_rinex_obs
from tests._data import data_path

hatanaka = pytest.importorskip("hatanaka", reason="pip install 'companion[rinex]'")

OBS = data_path("rtklib-testdata-geonet-2005/rinex/07590920.05o")
NAV = data_path("rtklib-testdata-geonet-2005/rinex/07590920.05n")


def _same_epochs(a, b):
    assert len(a) == len(b)
    for ea, eb in zip(a, b):
        assert ea.t_gps == eb.t_gps and len(ea.observations) == len(eb.observations)
        for oa, ob in zip(ea.observations, eb.observations):
            assert oa.sat == ob.sat and oa.signal == ob.signal
            for f in ("pseudorange_m", "carrier_cycles"):
                va, vb = getattr(oa, f), getattr(ob, f)
                assert (np.isnan(va) and np.isnan(vb)) or va == vb


@pytest.mark.real_data
@pytest.mark.parametrize("name,compression", [("07590920.05d", "none"), ("07590920.05d.gz", "gz"),
                                              ("07590920.05o.gz", "gz-plain"), ("07590920.05d.Z", "Z")])
def test_compressed_observation_files_read_as_the_plain_one(tmp_path, name, compression):
    if compression == "gz-plain":
        import gzip
        data = gzip.compress(OBS.read_bytes())
    elif compression == "Z":
        try:
            data = hatanaka.compress(OBS, compression="Z")
        except Exception as exc:                       # needs the 'compress' program or ncompress
            pytest.skip(f"no Unix compress here: {exc}")
    else:
        data = hatanaka.compress(OBS, compression=compression)
    p = tmp_path / name
    p.write_bytes(data)
    h_plain, plain = read_rinex_obs(OBS)
    h_c, comp = read_rinex_obs(p)
    assert h_c["marker"] == h_plain["marker"] and np.array_equal(h_c["approx_position_e"], h_plain["approx_position_e"])
    _same_epochs(plain, comp)


@pytest.mark.real_data
def test_gzipped_navigation_file(tmp_path):
    import gzip
    p = tmp_path / "07590920.05n.gz"
    p.write_bytes(gzip.compress(NAV.read_bytes()))
    assert [e.sat for e in read_rinex_nav(p)] == [e.sat for e in read_rinex_nav(NAV)]


def test_a_corrupt_compressed_file_is_a_clear_error(tmp_path):
    p = tmp_path / "broken.05d"
    p.write_bytes(b"this is not a Hatanaka file\n")
    with pytest.raises((ValueError, OSError)) as e:
        read_rinex_obs(p)
    assert "broken.05d" in str(e.value) or "RINEX" in str(e.value) or "decompress" in str(e.value)
