"""The status page (companion.status_page): its JSON over a real HTTP socket on 127.0.0.1, bounded
requests, and the page rendered by a real headless browser (Debian's chromium)."""
from __future__ import annotations

import asyncio
import json
import re
import shutil
import socket
import subprocess
import threading
import urllib.error
import urllib.request

import numpy as np
import pytest

from companion.messages import NavSolution
from companion.status_page import StatusBoard, StatusPageServer


def _solution(t: float, sigma_h: float, hpl: float, fix: str = "fixed") -> NavSolution:
    s = sigma_h / np.sqrt(2.0)
    return NavSolution(t, np.array([-3976219.7, 3382372.5, 3652513.1]), np.zeros(3), np.eye(3),
                       np.array([s, s, 2 * s]), np.full(3, 0.05), np.full(3, 1e-3), "nav",
                       extras={"inject": True, "hpl_m": hpl, "mode": "tight"}, fix_state=fix, fix_ratio=7.5)


def _board() -> StatusBoard:
    b = StatusBoard()
    for k in range(120):
        b.add_solution(_solution(1.4e9 + k, 0.02 + 0.3 * np.exp(-k / 20), 0.1 + 1.5 * np.exp(-k / 20)))
        b.add_solution(_solution(1.4e9 + k + 0.5, 9.0, 9.0))      # same second: not a new point
    b.set_aid_status({"sources": {"pseudorange": {"t_gps": 1.4e9 + 119, "fused": True,
                                                  "labels": ["G05", "G12", "G25", "G29", "G31"],
                                                  "test_ratio": [0.1, 0.3, 0.05, 0.7, 3.2],
                                                  "accepted": [True, True, True, True, False],
                                                  "rows_fused": 4, "rows_rejected": 1},
                               # double differences name two satellites, the reference (G05) among them
                               "rtk_phase": {"t_gps": 1.4e9 + 119, "fused": True,
                                             "labels": ["E11-E05 L1C phase", "E12-E05 L1C phase"],
                                             "test_ratio": [0.2, 0.1], "accepted": [True, True]}}})
    b.add_event(6, "CC: RTK fixed (ratio 7.5)")
    b.add_event(4, "CC: <script>alert(1)</script> escaped")
    b.set_health({"filter": {"status": "nav", "mode": "tight", "reset_counter": 0,
                             "satellites_by_system": {"G": 4, "E": 6}}, "uptime_s": 120})
    return b


@pytest.fixture
def served():
    """The server on a free port, in a thread with its own event loop (a browser process is the client)."""
    board = _board()
    loop = asyncio.new_event_loop()
    server = StatusPageServer(board, "127.0.0.1", 0)
    ready = threading.Event()

    def run():
        asyncio.set_event_loop(loop)
        loop.run_until_complete(server.start())
        ready.set()
        loop.run_forever()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    assert ready.wait(5)
    yield board, server
    asyncio.run_coroutine_threadsafe(server.close(), loop).result(5)
    loop.call_soon_threadsafe(loop.stop)
    th.join(5)


def _get(server, path: str):
    return urllib.request.urlopen(f"http://127.0.0.1:{server.port}{path}", timeout=5)


def test_status_json_and_routes(served):
    board, server = served
    st = json.loads(_get(server, "/status.json").read())
    assert len(st["history"]) == 120                          # one point per second of GPS time
    assert st["last"]["fix_state"] == "fixed" and st["last"]["sigma_h_m"] == pytest.approx(0.0206, abs=1e-3)
    assert st["satellites_used"] == 7                         # G31 was rejected; E05 is the DDs' reference
    assert st["satellites_by_system"] == {"G": 4, "E": 6}
    assert st["sources"]["pseudorange"]["test_ratio"][-1] == 3.2
    assert json.loads(_get(server, "/health.json").read())["filter"]["mode"] == "tight"
    assert b"<title>companion status</title>" in _get(server, "/").read()
    with pytest.raises(urllib.error.HTTPError) as e:
        _get(server, "/etc/passwd")
    assert e.value.code == 404


def test_bad_requests_are_bounded(served):
    _, server = served
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
        s.sendall(b"POST / HTTP/1.1\r\nHost: x\r\n\r\n")
        assert s.recv(100).startswith(b"HTTP/1.1 405")
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
        s.sendall(b"GET / HTTP/1.1\r\n" + b"X-Junk: " + b"a" * 70000)   # no end of headers, over the limit
        assert s.recv(100) == b""                               # dropped, not buffered without bound
    assert server.counters["bad requests"] == 2
    assert _get(server, "/status.json").status == 200           # still serving


def test_page_renders_in_headless_chromium(served, tmp_path):
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("Debian's chromium is not installed (scripts/test.sh installs it when run as root)")
    _, server = served
    url = f"http://127.0.0.1:{server.port}/"
    common = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=4000"]
    dom = subprocess.run(common + ["--dump-dom", url], capture_output=True, text=True, timeout=120).stdout
    def text(elem_id):             # the element's text, whatever the attribute order
        m = re.search(rf'<[^>]*\bid="{elem_id}"[^>]*>([^<]*)<', dom)
        return m.group(1) if m else None

    assert text("status") == "nav" and text("fix") == "fixed" and text("inject") == "yes"
    assert text("sigma_h") == "0.02 m" and text("hpl") == "0.10 m" and text("sats") == "7 of 10 tracked (G 4, E 6)"
    assert text("mode") == "tight" and text("ratio") == "7.5"
    assert ">G31<" in dom and "rejected" in dom
    assert "RTK fixed (ratio 7.5)" in dom
    assert "<script>alert(1)" not in dom and "&lt;script&gt;alert(1)" in dom
    assert "<path d=\"M" in dom                                   # the sigma/HPL plot was drawn
    png = tmp_path / "status.png"
    subprocess.run(common + ["--window-size=1280,900", f"--screenshot={png}", url], capture_output=True,
                   timeout=120)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
