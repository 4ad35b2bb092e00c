"""Ctrl-C during ``python -m sitl fly``: every process it started stops, the exit status is non-zero
and the JSON says the run was interrupted (issue 9)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _session_pids(sid: int) -> list[int]:
    """Live processes of session ``sid`` (zombies excluded)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if fields[0] != "Z" and int(fields[3]) == sid:   # state, ppid, pgrp, session
            out.append(int(d.name))
    return out


@pytest.mark.slow
def test_sigint_stops_every_process_and_says_interrupted(tmp_path):
    js = tmp_path / "fly.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "sitl", "fly", "--duration", "60", "--out", str(tmp_path / "fly"),
         "--json", str(js)], cwd=str(REPO), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        start_new_session=True, text=True)
    lines = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "flying" in line and "estimates" in line:   # the first status line: everything runs
                break
        assert any("estimates" in ln for ln in lines), "".join(lines)
        assert len(_session_pids(proc.pid)) >= 2, "the companion should be running beside the harness"
        # SIGINT to the harness alone (not its process group): it must stop its children itself
        os.kill(proc.pid, signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, "".join(lines) + rest
    assert "INTERRUPTED" in rest
    time.sleep(0.5)
    assert _session_pids(proc.pid) == [], "processes of the run still alive"
    obj = json.loads(js.read_text())
    assert obj["interrupted"] is True
    assert obj["details"]["flown_s"] < 60
