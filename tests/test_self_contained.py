"""The checkout is self-contained (issue 9): the real-data tests find their data in the repository
whatever the working directory and HOME are, none of them skips, and no file of the tree names a
folder of the machine it was written on."""
from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _tracked_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
        return [REPO / f for f in out.decode().split("\0") if f]
    except (OSError, subprocess.CalledProcessError):     # an exported tree without git
        return [p for p in REPO.rglob("*") if p.is_file() and ".git" not in p.parts and ".venv" not in p.parts]


@pytest.mark.timeout(660)          # the run inside has its own 600-s limit (every real-data test, one process)
def test_real_data_tests_run_from_anywhere_and_none_skips(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    junit = tmp_path / "real_data.xml"
    env = dict(os.environ, HOME=str(home), PYTHONDONTWRITEBYTECODE="1")
    env.pop("PYTHONPATH", None)
    p = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "real_data",
                        f"--junitxml={junit}", "--rootdir", str(REPO), "-c", str(REPO / "pyproject.toml"),
                        str(REPO / "tests")], cwd=str(tmp_path), env=env, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    suite = ET.parse(junit).getroot()
    suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
    tests, skipped = int(suite.get("tests")), int(suite.get("skipped"))
    files = {tc.get("classname", "").split(".")[-1] for tc in suite.iter("testcase")}
    print(f"real-data tests run from {tmp_path}: {tests}, skipped {skipped}, files {sorted(files)}")
    assert skipped == 0
    # every recorded data set is exercised: GEONET RINEX, the F9P UBX log, the RTCM3 streams
    assert {"test_spp_dgps_geonet", "test_ephemeris", "test_io_ubx", "test_io_rtcm"} <= files
    assert tests >= 30


def test_no_machine_path_in_the_tree():
    """Nothing tracked names this checkout's folder, the folder beside it (where a developer's
    shared data lives) or HOME: data is found relative to the package or the repository."""
    system = {"/", "/tmp", "/var", "/usr", "/opt", "/etc", "/home", "/srv", "/mnt", "/dev"}
    needles = {str(REPO), str(REPO.parent), str(Path.home())} - system
    hits = []
    for f in _tracked_files():
        try:
            text = f.read_text(errors="ignore")
        except (OSError, UnicodeError):
            continue
        for n in needles:
            # a needle followed by a path separator: '/work' inside '/workspace' does not count
            if n + "/" in text:
                hits.append(f"{f.relative_to(REPO)}: {n}")
    assert not hits, hits
