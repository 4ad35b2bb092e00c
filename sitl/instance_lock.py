"""Reserving a simulator instance number (PX4 SITL, ArduCopter SITL) across processes.

An instance is free when its ports (and PX4's own lock file) are; but between one test worker
finding instance N free and its simulator binding N's ports, another worker can find the same.
Each choice is therefore made under an flock on ``<tmp>/companion-<kind>-instance-N.lock``, held
until the simulator stops (the kernel drops it if the process dies)."""
from __future__ import annotations

import fcntl
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable


def reserve_instance(kind: str, max_instance: int, usable: Callable[[int], bool],
                     first: int = 0) -> tuple[int, BinaryIO]:
    """(the first instance from ``first`` on that no other process has reserved and ``usable``
    accepts, its held lock)."""
    for i in range(first, max_instance):
        fh = open(Path(tempfile.gettempdir()) / f"companion-{kind}-instance-{i}.lock", "ab")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        if usable(i):
            return i, fh
        release(fh)
    raise RuntimeError(f"no free {kind} instance among {first}..{max_instance - 1}")


def release(fh: BinaryIO | None) -> None:
    if fh is not None and not fh.closed:
        fcntl.flock(fh, fcntl.LOCK_UN)
        fh.close()


__all__ = ["reserve_instance", "release"]
