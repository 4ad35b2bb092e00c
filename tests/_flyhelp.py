"""Shared helpers for the loopback tests (emulated autopilot + caster + `companion run`)."""
from __future__ import annotations

import asyncio
import json

from companion.io.fieldlog import read_field_log


def run_fly(tmp_path, **kw) -> dict:
    from sitl.fly import fly
    kw.setdefault("out_dir", str(tmp_path / "fly"))
    return asyncio.run(fly(**kw))


def final_health(field_log_dir) -> dict:
    """The health report the service wrote into its field log at shutdown."""
    h = {}
    events = []
    for rec in read_field_log(field_log_dir):
        if rec.kind == "event":
            obj = json.loads(rec.payload)
            events.append(obj)
            if obj.get("event") in ("stop", "health"):
                h = obj["health"]
    return {"health": h, "events": events}
