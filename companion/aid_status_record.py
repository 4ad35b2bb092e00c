"""The per aid source status as a record of its own: field log kind ``aid_status`` and MQTT
``<prefix>/aid_status``.

Payload: compact JSON (UTF-8, no spaces), one object per record::

    {"v": 1, "t_gps": ..., "status": "nav", "inject": true, "sigma_h_m": ..., "hpl_m": ...,
     "hpl_cov_m": ..., "hpl_ss_m": ..., "integrity": "ok",
     "sources": {"pseudorange": {"t_gps": ..., "fused": true, "labels": [...], "innovation": [...],
                                 "innovation_var": [...], "test_ratio": [...], "accepted": [...],
                                 "rows_fused": ..., "rows_rejected": ...}, ...}}

``sources`` holds each source's *last* update (companion.nav.aid_status: PX4's
``estimator_aid_src_*``); a source that did not update since the previous record repeats its
``t_gps`` (a reader keeps one entry per source and time).  Numbers are rounded (4 decimals,
times 3), non-finite ones are ``null``.  Records are paced by the solutions' GPS time (one per
``1 / rate_hz`` slot, like the other outputs), so they are a pure function of the pipeline's state:
``companion replay`` recomputes them and can compare them with the logged ones.
"""
from __future__ import annotations

import json
import math

AID_STATUS_RECORD_VERSION = 1
KIND = "aid_status"


def json_number(x, nd: int = 4):
    """``x`` rounded to ``nd`` decimals for JSON, None when it is not a finite number."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return round(x, nd) if math.isfinite(x) else None


_r = json_number


def aid_status_dict(pipeline, sol) -> dict:
    """The record's object for the pipeline's current aid-source book and solution ``sol``."""
    sig = sol.sigma_r_n_m
    x = sol.extras
    sources = {}
    for name, st in sorted(pipeline.engine.aid.sources.items()):
        sources[name] = {"t_gps": _r(st.t_gps, 3), "fused": bool(st.fused), "labels": [str(s) for s in st.labels],
                         "innovation": [_r(v) for v in st.innovation.tolist()],
                         "innovation_var": [_r(v) for v in st.innovation_var.tolist()],
                         "test_ratio": [_r(v) for v in st.test_ratio.tolist()],
                         "accepted": [bool(a) for a in st.accepted.tolist()],
                         "rows_fused": int(st.rows_fused), "rows_rejected": int(st.rows_rejected)}
    return {"v": AID_STATUS_RECORD_VERSION, "t_gps": _r(sol.t_gps, 3), "status": sol.status,
            "inject": bool(x.get("inject")), "sigma_h_m": _r(math.hypot(float(sig[0]), float(sig[1]))),
            "hpl_m": _r(x.get("hpl_m")), "hpl_cov_m": _r(x.get("hpl_cov_m")), "hpl_ss_m": _r(x.get("hpl_ss_m")),
            "integrity": str(x.get("integrity", "")), "sources": sources}


def encode_aid_status(obj: dict) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def decode_aid_status(payload: bytes) -> dict | None:
    """The object of a record, or None for a version this one does not know."""
    obj = json.loads(bytes(payload).decode())
    return obj if isinstance(obj, dict) and obj.get("v") == AID_STATUS_RECORD_VERSION else None


class AidStatusPacer:
    """One record per ``1 / rate_hz`` slot of the solutions' GPS time (0 = never)."""

    def __init__(self, rate_hz: float):
        self.rate_hz = float(rate_hz)
        self._slot = None

    def due(self, t_gps: float) -> bool:
        if self.rate_hz <= 0.0 or not math.isfinite(t_gps):
            return False
        slot = math.floor(t_gps * self.rate_hz)
        if slot == self._slot:
            return False
        self._slot = slot
        return True

    def records(self, pipeline, sols) -> list[tuple[dict, bytes]]:
        """(object, payload) of the records due for these solutions (in order; at most one each)."""
        out = []
        for sol in sols:
            if self.due(sol.t_gps):
                obj = aid_status_dict(pipeline, sol)
                out.append((obj, encode_aid_status(obj)))
        return out


__all__ = [
    "AID_STATUS_RECORD_VERSION",
    "KIND",
    "AidStatusPacer",
    "aid_status_dict",
    "decode_aid_status",
    "encode_aid_status",
]
