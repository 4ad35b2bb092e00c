"""`python -m sitl fly` end to end, short: estimates arrive at the configured rate, close to the truth."""
import json
import subprocess
import sys



def test_fly_short_run_scores(tmp_path):
    out = tmp_path / "fly"
    js = tmp_path / "fly.json"
    p = subprocess.run([sys.executable, "-m", "sitl.fly", "fly", "--duration", "30", "--speedup", "2",
                        "--out", str(out), "--json", str(js)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    r = json.loads(js.read_text())
    for k in ("estimates_received", "estimate_rate_hz", "estimate_rate_fraction", "rms_3d_m", "rms_h_m", "p95_3d_m",
              "latency_ms_p50", "latency_ms_p99", "companion_cpu_pct", "companion_rss_mb"):
        assert k in r
    d = r["details"]
    # initialisation takes ~3 s of the 30: the rest arrives at the configured 25 Hz
    assert d["estimate_rate_fraction_after_first"] > 0.9
    assert r["rms_h_m"] < 1.5 and r["p95_3d_m"] < 3.0
    assert r["latency_ms_p99"] < 50.0
    assert d["companion_exit_code"] == 0
    assert any("nav init" in t for t in d["statustext"])


def test_stock_autopilot_without_raw_gnss_gets_a_loosely_coupled_estimate(tmp_path):
    """Issue 3: with GPS_RAW_INT only (no receiver tunnel, no corrections) the service falls back to
    loose coupling, says so, and still injects estimates."""
    from tests._flyhelp import final_health, run_fly
    r = run_fly(tmp_path, duration_s=30.0, speedup=2.0, gnss_source="none", use_caster=False)
    d = r.get("details", r)
    print({k: r[k] for k in ("estimates_received", "estimate_rate_fraction", "rms_h_m", "p95_3d_m")})
    assert r["estimates_received"] > 0.7 * 25 * 30
    # announced to the ground station: initialised from GPS_RAW_INT and navigating in loose mode
    assert any("GPS_RAW_INT fix (loose)" in t for t in d["statustext"])
    assert any("nav OK loose" in t for t in d["statustext"])
    # GPS_RAW_INT is a metre-class fix: the fused estimate is that good, not better
    assert r["rms_h_m"] < 5.0
    health = final_health(d["field_log_dir"])["health"]
    assert health, "the service wrote no health report"
