"""CPU cost per byte of the RTCM framer and decoder: real RTCM against false-sync floods.

``python -m sitl.rtcm_flood [--json PATH]`` prints, for the framer alone and for the full decoder
(what the service runs on every correction byte), the rate in bytes per CPU second of a real
base-station stream and of hostile streams: ``D3 03`` repeated (the false sync of issue 14),
``D3 00 FF 43 50`` (a false sync that passes the reserved-bit, length and message-number checks, so
only the CRC can reject it) and random bytes.  The ratio real/flood is the flood's amplification.
"""
from __future__ import annotations

import argparse
import json
import logging
import random
import time
from pathlib import Path

from companion.io.rtcm import RtcmDecoder, RtcmFramer

REAL = Path(__file__).resolve().parents[1] / "tests/data/qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm"


def flood_streams(n: int, seed: int = 1) -> dict[str, bytes]:
    rng = random.Random(seed)
    # a crafted false sync that only the CRC can reject: reserved bits 0, length 255, message
    # number 1077 (MSM7, variable length; 0x435): D3 00 FF 43 50, one every 5 bytes
    crafted = bytes([0xD3, 0x00, 0xFF, 0x43, 0x50])
    return {"d3_03": b"\xd3\x03" * (n // 2),
            "crafted_1077": crafted * (n // len(crafted)),
            "random": bytes(rng.getrandbits(8) for _ in range(n))}


def cpu_rate(make, data: bytes, chunk: int = 1024, min_cpu_s: float = 0.2) -> float:
    """Bytes per CPU second of ``make().feed`` over ``data`` in ``chunk``-byte pieces (repeated
    until ``min_cpu_s`` of process CPU time has been spent)."""
    total = 0
    t0 = time.process_time()
    while True:
        obj = make()
        for i in range(0, len(data), chunk):
            obj.feed(data[i:i + chunk])
        total += len(data)
        dt = time.process_time() - t0
        if dt >= min_cpu_s:
            return total / dt


def measure(real: bytes | None = None, flood_bytes: int = 20000, min_cpu_s: float = 0.2,
            framer_cls=RtcmFramer, decoder_cls=RtcmDecoder) -> dict:
    real = REAL.read_bytes() if real is None else real
    out: dict = {}
    for label, make in (("framer", framer_cls), ("decoder", lambda: decoder_cls(week_hint=2240))):
        rates = {"real": cpu_rate(make, real, min_cpu_s=min_cpu_s)}
        for name, data in flood_streams(flood_bytes).items():
            rates[name] = cpu_rate(make, data, min_cpu_s=min_cpu_s)
        out[label] = {k: round(v) for k, v in rates.items()}
        out[label + "_amplification"] = {k: round(rates["real"] / v, 2) for k, v in rates.items() if k != "real"}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m sitl.rtcm_flood")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)          # the floods' rate-limited warnings, per framer
    res = measure(min_cpu_s=1.0)
    from companion.io.crc24q import BACKEND
    res["crc_backend"] = BACKEND
    print(json.dumps(res, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
