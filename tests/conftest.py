"""Suite-wide rules.

* The repository root is importable (``tests._data``, ``tests._flyhelp``) whatever the working
  directory, so the suite runs from anywhere.
* A test marked ``real_data`` reads recorded data shipped in ``tests/data``; in CI (``CI`` set)
  it must never skip: a skipped real-data test is reported as a failure there (the data is part
  of the checkout, and CI installs the tools some of them also need, RTKLIB among them).  On a
  contributor's machine without those tools the skip stays a skip, with its reason.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.skipped and os.environ.get("CI") and item.get_closest_marker("real_data") is not None:
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"real-data test skipped ({reason}): tests/data must make every real-data test run"
