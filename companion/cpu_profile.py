"""CPU accounting of the running service, for measurements only (``COMPANION_CPU_PROFILE=PATH``).

Sampling profilers count the idle ``epoll_wait`` as busy in some containers; this counts CPU time
instead: every event-loop callback is timed with ``time.thread_time_ns`` and charged to what it
runs (a task's name, a reader or timer callback's qualified name), the loop's passes are counted,
and a few named methods get inclusive timers of their own (the receive path's pieces).  At exit
the totals go to PATH as JSON: CPU seconds and calls per key, the process and main-thread CPU, and
the other threads' (the field-log flusher) as the difference, and the garbage collector's passes
per generation (CPU, count, the longest).  The timers cost ~1 us per call;
use the figures as a breakdown, not as the service's CPU (measure that without this).
"""
from __future__ import annotations

import asyncio
import atexit
import functools
import json
import os
import threading
import time
from collections import defaultdict

_cpu = defaultdict(int)          # key -> thread CPU ns
_calls = defaultdict(int)
_state = {"passes": 0, "t0_wall": 0.0, "t0_proc": 0.0, "t0_main": 0, "path": None, "installed": False}


def _key_of(cb) -> str:
    task = getattr(cb, "__self__", None)
    if isinstance(task, asyncio.Task):
        return "task " + task.get_name()
    fn = getattr(cb, "__func__", cb)
    return "cb " + getattr(fn, "__qualname__", repr(fn))


def _timed(name: str, fn):
    tt = time.thread_time_ns

    @functools.wraps(fn)
    def wrapper(*a, **kw):
        t0 = tt()
        try:
            return fn(*a, **kw)
        finally:
            _cpu[name] += tt() - t0
            _calls[name] += 1
    return wrapper


def _patch_methods() -> None:
    from . import pipeline, service
    from .io import fieldlog, mavlink, mavlink_fast, serial_control
    targets = [(service.Service, "_record"), (service.Service, "_outputs"),
               (pipeline.NavPipeline, "feed_mavlink_record"), (pipeline.NavPipeline, "_imu"),
               (pipeline.NavPipeline, "_feed_messages"),
               (mavlink.MavlinkLink, "_handle"), (mavlink.MavlinkLink, "_drain"), (mavlink.MavlinkLink, "send"),
               (mavlink_fast.DatagramParser, "feed"), (fieldlog.FieldLogWriter, "write"),
               (fieldlog.FieldLogWriter, "_sync"), (serial_control.SerialControlTunnel, "poll"),
               (serial_control.PortClaim, "step")]
    for cls, name in targets:
        fn = getattr(cls, name, None)
        if fn is not None:
            setattr(cls, name, _timed(f"{cls.__name__}.{name}", fn))


def install(path: str) -> None:
    """Start accounting (call once, before the event loop runs the service)."""
    if _state["installed"]:
        return
    _state.update(installed=True, path=path, t0_wall=time.monotonic(), t0_proc=time.process_time(),
                  t0_main=time.thread_time_ns())
    tt = time.thread_time_ns
    handle_run = asyncio.events.Handle._run

    def _run(self):
        k = _key_of(self._callback)      # before: a callback that cancels its own handle clears it
        t0 = tt()
        try:
            return handle_run(self)
        finally:
            _cpu[k] += tt() - t0
            _calls[k] += 1
    asyncio.events.Handle._run = _run
    run_once = asyncio.base_events.BaseEventLoop._run_once

    def _run_once(self):
        _state["passes"] += 1
        return run_once(self)
    asyncio.base_events.BaseEventLoop._run_once = _run_once
    _patch_methods()
    import gc

    def _gc(phase, info):
        if phase == "start":
            _state["gc_t0"] = tt()
        else:
            g = info["generation"]
            dt = tt() - _state.get("gc_t0", tt())
            _cpu[f"gc generation {g}"] += dt
            _calls[f"gc generation {g}"] += 1
            _state["gc_max_ns"] = max(_state.get("gc_max_ns", 0), dt)
    gc.callbacks.append(_gc)
    atexit.register(dump)


def dump() -> None:
    path = _state["path"]
    if not path or threading.current_thread() is not threading.main_thread():
        return
    wall = time.monotonic() - _state["t0_wall"]
    proc = time.process_time() - _state["t0_proc"]
    main = (time.thread_time_ns() - _state["t0_main"]) * 1e-9
    keys = sorted(_cpu, key=lambda k: -_cpu[k])
    out = {"wall_s": round(wall, 3), "process_cpu_s": round(proc, 3), "main_thread_cpu_s": round(main, 3),
           "other_threads_cpu_s": round(proc - main, 3), "loop_passes": _state["passes"],
           "loop_passes_per_s": round(_state["passes"] / max(wall, 1e-9), 1),
           "gc_longest_ms": round(_state.get("gc_max_ns", 0) * 1e-6, 2),
           "by_key": {k: {"cpu_s": round(_cpu[k] * 1e-9, 4), "calls": _calls[k],
                          "pct_of_core": round(100.0 * _cpu[k] * 1e-9 / max(wall, 1e-9), 3),
                          "us_per_call": round(_cpu[k] * 1e-3 / max(_calls[k], 1), 2)} for k in keys}}
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(out, f, indent=1)
    os.replace(tmp, path)
    _state["path"] = None        # once


__all__ = ["install", "dump"]
