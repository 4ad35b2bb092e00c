"""Monte Carlo runs in worker processes: one deterministic function call per seed.

Each run depends only on its arguments (its seed among them), so the results do not depend on the
number of workers; they come back in submission order.
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor


def run_all(fn, args_list: list[tuple], jobs: int = 0, progress=None) -> list:
    """``[fn(*args) for args in args_list]``, in ``jobs`` worker processes (0: one per core).
    ``progress(done, total, elapsed_s)`` is called as results arrive."""
    t_start = time.perf_counter()
    total = len(args_list)
    jobs = jobs or min(total, os.cpu_count() or 1)
    results = []
    if jobs <= 1:
        for args in args_list:
            results.append(fn(*args))
            if progress:
                progress(len(results), total, time.perf_counter() - t_start)
        return results
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        for f in [pool.submit(fn, *args) for args in args_list]:
            results.append(f.result())
            if progress:
                progress(len(results), total, time.perf_counter() - t_start)
    return results
