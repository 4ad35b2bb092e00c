"""The long fuzz run (issue 14): the targets of ``tests/fuzz_targets.py`` a million times.

    python -m tests.fuzz                          # 1,000,000 inputs shared by every target
    python -m tests.fuzz -n 20000 --targets ubx,rtcm --seed 3
    python -m tests.fuzz --replay DIR/rtcm-000123.bin     # re-run one saved input (its target from the name)

Run from the repository root (``tests`` is found from the working directory).  Per target it
reports the inputs and bytes run, the *uncaught exceptions* (anything but the documented error, or
a broken bound: see ``tests/fuzz_targets.py``) with the first few inputs saved as reproducers
(``--out``, default ``<tmp>/companion-fuzz``), the slowest input per byte (us/B, inputs of at
least 64 bytes, so fixed set-up costs do not dominate) and the slowest input, and memory: the
peak of Python allocations while one input runs (``tracemalloc`` on every ``--trace-every``-th
input, since tracing slows the run down) and the process's peak RSS after the target.  A long
run's maxima include the scheduler and lazy imports, so the slowest and the most allocating input
are run again at the end (best of 5 / 3: the ``rerun`` columns) and saved as
``<target>-slowest.bin`` / ``<target>-heaviest.bin`` (``--replay`` runs them).
Exit status 1 when any target had an uncaught exception.
"""
from __future__ import annotations

import argparse
import json
import logging
import random
import resource
import sys
import tempfile
import time
import tracemalloc
import traceback
import zlib
from pathlib import Path

from tests.fuzz_targets import TARGETS

KEEP_REPRODUCERS = 5
MIN_BYTES_FOR_RATE = 64
PROGRESS_INTERVAL_S = 10.0


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0       # Linux: kB


def run_target(name: str, n: int, seed: int, out: Path, trace_every: int, progress) -> dict:
    target = TARGETS[name]
    rng = random.Random(seed ^ zlib.crc32(name.encode()))
    rep = {"target": name, "doc": target.doc, "inputs": 0, "bytes": 0, "uncaught": 0, "kinds": {},
           "reproducers": [], "max_us_per_byte": 0.0, "max_us_per_byte_input_len": 0,
           "max_ms_per_input": 0.0, "max_ms_input_len": 0, "peak_traced_kb": 0.0,
           "peak_traced_bytes_per_input_byte": 0.0, "traced_inputs": 0}
    slowest = heaviest = b""
    try:                                    # warm-up, untimed: lazy imports (numpy, pyrtcm) and caches
        target.run(target.generate(random.Random(0)))
    except Exception:
        pass
    t_start = last = time.monotonic()
    for i in range(n):
        data = target.generate(rng)
        trace = trace_every > 0 and i % trace_every == 0
        if trace:
            tracemalloc.start()
            tracemalloc.reset_peak()
        t0 = time.perf_counter()
        try:
            target.run(data)
            failed = None
        except Exception as exc:            # what the contract forbids: count it, keep the input
            failed = exc
        dt = time.perf_counter() - t0
        if trace:
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            rep["traced_inputs"] += 1
            rep["peak_traced_kb"] = max(rep["peak_traced_kb"], peak / 1024.0)
            if len(data) >= MIN_BYTES_FOR_RATE and peak / len(data) > rep["peak_traced_bytes_per_input_byte"]:
                rep["peak_traced_bytes_per_input_byte"], heaviest = peak / len(data), data
        rep["inputs"] += 1
        rep["bytes"] += len(data)
        if dt * 1e3 > rep["max_ms_per_input"]:
            rep["max_ms_per_input"], rep["max_ms_input_len"] = dt * 1e3, len(data)
        if len(data) >= MIN_BYTES_FOR_RATE and dt * 1e6 / len(data) > rep["max_us_per_byte"]:
            rep["max_us_per_byte"], rep["max_us_per_byte_input_len"] = dt * 1e6 / len(data), len(data)
            slowest = data
        if failed is not None:
            rep["uncaught"] += 1
            kind = f"{type(failed).__name__}: {str(failed)[:120]}"
            rep["kinds"][kind] = rep["kinds"].get(kind, 0) + 1
            if len(rep["reproducers"]) < KEEP_REPRODUCERS:
                out.mkdir(parents=True, exist_ok=True)
                p = out / f"{name}-{i:07d}.bin"
                p.write_bytes(data)
                p.with_suffix(".txt").write_text("".join(traceback.format_exception(failed)))
                rep["reproducers"].append(str(p))
        now = time.monotonic()
        if now - last >= PROGRESS_INTERVAL_S:
            last = now
            progress(f"{name}: {i + 1}/{n} inputs, {(i + 1) / (now - t_start):.0f}/s, "
                     f"{rep['uncaught']} uncaught")
    rep["seconds"] = round(time.monotonic() - t_start, 1)
    _recheck(target, name, slowest, heaviest, out, rep)
    rep["peak_rss_mb"] = round(_rss_mb(), 1)
    return rep


def _recheck(target, name: str, slowest: bytes, heaviest: bytes, out: Path, rep: dict) -> None:
    """The maxima of a long run include the scheduler (another process, a page fault) and lazy
    imports: run the slowest and the most allocating input again (best of 5) and keep both."""
    out.mkdir(parents=True, exist_ok=True)
    if slowest:
        best = min(_timed(target, slowest) for _ in range(5))
        rep["slowest_rerun_us_per_byte"] = round(best * 1e6 / len(slowest), 2)
        (out / f"{name}-slowest.bin").write_bytes(slowest)
    if heaviest:
        tracemalloc.start()
        peaks = []
        for _ in range(3):
            tracemalloc.reset_peak()
            try:
                target.run(heaviest)
            except Exception:
                pass
            peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        rep["heaviest_rerun_peak_kb"] = round(min(peaks) / 1024.0, 1)
        rep["heaviest_rerun_bytes_per_input_byte"] = round(min(peaks) / len(heaviest), 1)
        (out / f"{name}-heaviest.bin").write_bytes(heaviest)


def _timed(target, data: bytes) -> float:
    t0 = time.perf_counter()
    try:
        target.run(data)
    except Exception:
        pass
    return time.perf_counter() - t0


def replay(path: Path) -> int:
    name = path.name.rsplit("-", 1)[0]          # rtcm-0000123.bin, rtcm-slowest.bin
    if name not in TARGETS:
        print(f"error: {path.name}: the name does not start with a target ({', '.join(TARGETS)})", file=sys.stderr)
        return 2
    TARGETS[name].run(path.read_bytes())           # raises with its traceback if it still fails
    print(f"{path}: {name} passes")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.fuzz", description=__doc__.splitlines()[0])
    ap.add_argument("-n", "--inputs", type=int, default=1_000_000, help="inputs in all, shared equally")
    ap.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated ({', '.join(TARGETS)})")
    ap.add_argument("--seed", type=int, default=14)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "companion-fuzz",
                    help="where reproducers go")
    ap.add_argument("--trace-every", type=int, default=100, help="trace allocations of every N-th input (0: never)")
    ap.add_argument("--json", type=Path, help="write the report as JSON here")
    ap.add_argument("--replay", type=Path, help="run one saved input again")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)              # the decoders' rate-limited warnings are expected
    if args.replay:
        return replay(args.replay)
    names = [t for t in args.targets.split(",") if t]
    unknown = [t for t in names if t not in TARGETS]
    if unknown:
        ap.error(f"unknown target(s) {', '.join(unknown)}")
    per = [args.inputs // len(names) + (1 if k < args.inputs % len(names) else 0) for k in range(len(names))]

    def progress(msg):
        print(msg, file=sys.stderr, flush=True)

    reports = []
    for name, n in zip(names, per):
        progress(f"{name}: {n} inputs ({TARGETS[name].doc})")
        r = run_target(name, n, args.seed, args.out, args.trace_every, progress)
        reports.append(r)
        progress(f"{name}: done in {r['seconds']} s, {r['uncaught']} uncaught")
    print(f"{'target':14} {'inputs':>9} {'MB':>7} {'uncaught':>8} {'max us/B':>9} {'rerun':>7} {'max ms':>7} "
          f"{'peak kB':>8} {'B/B':>6} {'rerun':>6} {'RSS MB':>7}")
    for r in reports:
        print(f"{r['target']:14} {r['inputs']:9d} {r['bytes'] / 1e6:7.1f} {r['uncaught']:8d} "
              f"{r['max_us_per_byte']:9.2f} {r.get('slowest_rerun_us_per_byte', 0.0):7.2f} "
              f"{r['max_ms_per_input']:7.1f} {r['peak_traced_kb']:8.0f} "
              f"{r['peak_traced_bytes_per_input_byte']:6.1f} {r.get('heaviest_rerun_bytes_per_input_byte', 0.0):6.1f} "
              f"{r['peak_rss_mb']:7.1f}")
        for kind, count in r["kinds"].items():
            print(f"    {count} x {kind}")
        for p in r["reproducers"]:
            print(f"    reproducer: {p}")
    total = sum(r["inputs"] for r in reports)
    bad = sum(r["uncaught"] for r in reports)
    print(f"total: {total} inputs, {bad} uncaught exceptions (seed {args.seed})")
    if args.json:
        args.json.write_text(json.dumps({"seed": args.seed, "inputs": total, "uncaught": bad,
                                         "targets": reports}, indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
