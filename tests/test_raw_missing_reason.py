"""The pipeline says by name why it has no raw observations (issue 15): nothing from the receiver,
UBX without RXM-RAWX (a factory-default u-blox), RXM-RAWX without any ephemerides."""
from __future__ import annotations

import pytest

pyubx2 = pytest.importorskip("pyubx2")

from companion.config import Config  # noqa: E402
from companion.pipeline import NavPipeline  # noqa: E402
from tests._data import data_path  # noqa: E402

UBX = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20230919-114418.ubx")


def _frames(identity: str) -> bytes:
    with open(UBX, "rb") as fh:
        return b"".join(raw for raw, msg in pyubx2.UBXReader(fh, protfilter=pyubx2.UBX_PROTOCOL,
                                                            quitonerror=pyubx2.ERR_IGNORE)
                        if msg is not None and msg.identity == identity)


def test_nothing_then_nav_only_then_rawx_without_ephemerides():
    p = NavPipeline(Config())
    shorts = []

    def reason():
        short, hint = p.raw_missing_reason()
        shorts.append(short)
        return short, hint
    assert reason()[1] == "no UBX frame from the receiver on GPS1 (SERIAL_CONTROL)"
    nav = pyubx2.UBXMessage("NAV", "NAV-PVT", pyubx2.GET, iTOW=1000, fixType=3, numSV=9).serialize()
    p.feed("ubx", 0, nav * 3)
    short, hint = reason()
    assert "no RXM-RAWX" in short and "gnss configure" in hint
    p.feed("ubx", 1, _frames("RXM-RAWX"))
    assert p.counters["rover epochs"] > 0
    short, hint = reason()
    assert "SFRBX" in short and "no RXM-SFRBX" in hint
    p.feed("ubx", 2, _frames("RXM-SFRBX"))
    assert p.engine.ephemerides.sats
    assert reason()[0].startswith("no usable RXM-RAWX")
    # a STATUSTEXT carries 50 bytes, the service's "CC: " included: each short text fits
    assert len(set(shorts)) == 4 and all(len("CC: nav loose: " + s) <= 50 for s in shorts)
