"""``companion gnss --plot``: the offsets it draws, and the PNG it writes for every mode."""
from __future__ import annotations

import numpy as np
import pytest

from companion.gnss.pos_format import PosRecord
from companion.gnss.solution_plot import enu_offsets
from companion.nav.earth import C_n_e, ecef_to_geodetic
from tests._data import data_path

D = data_path("matrtklib-septentrio-static-2024")
BASE_XYZ = "-3817681.1213,3562839.4311,3650159.1593"
TRUTH_XYZ = "-3817681.3807,3562839.9785,3650158.3760"


def test_offsets_are_east_north_up_with_their_sigmas():
    ref = np.array([-3817681.3807, 3562839.9785, 3650158.3760])
    C = C_n_e(*ecef_to_geodetic(ref)[:2])                  # NED -> ECEF
    cov_ned = np.diag([0.01 ** 2, 0.02 ** 2, 0.05 ** 2])
    rec = PosRecord(0.0, ref + C @ np.array([1.0, 2.0, -3.0]), C @ cov_ned @ C.T, 1, 9)
    enu, sig = enu_offsets([rec], ref)
    assert np.allclose(enu[0], [2.0, 1.0, 3.0], atol=1e-9)
    assert np.allclose(sig[0], [0.02, 0.01, 0.05], atol=1e-12)


@pytest.mark.parametrize("mode", ["spp", "rtk"])
def test_cli_writes_the_png(tmp_path, mode):
    pytest.importorskip("matplotlib")
    from companion.cli import main
    png = tmp_path / f"{mode}.png"
    args = ["gnss", "--rover", str(D / "rover.crx.gz"), "--nav", str(D / "base.nav.gz"), "--sys", "G",
            f"--truth-xyz={TRUTH_XYZ}", "--mode", mode, "--plot", str(png)]
    if mode == "rtk":
        args += ["--base", str(D / "base.crx.gz"), f"--base-xyz={BASE_XYZ}"]
    assert main(args) == 0
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
