"""Where the tests find the recorded data: ``tests/data`` of this checkout, never a machine path."""
from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent / "data"


def data_path(relative: str) -> Path:
    """``tests/data/<relative>``; a missing file is an error (a real-data test must not skip)."""
    p = DATA_DIR / relative
    if not p.exists():
        raise FileNotFoundError(f"test data missing from the checkout: {p} (see tests/data/README.md)")
    return p
