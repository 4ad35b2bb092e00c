"""Simulator instance numbers are reserved under a lock: two test workers starting PX4 (or
ArduCopter) SITL in the same second cannot both take instance N before either binds its ports."""
from __future__ import annotations

import os

from sitl.instance_lock import release, reserve_instance


def test_a_reserved_instance_is_not_given_twice_until_released():
    kind = f"test-{os.getpid()}"
    a, lock_a = reserve_instance(kind, 5, lambda i: True)
    b, lock_b = reserve_instance(kind, 5, lambda i: True)
    assert (a, b) == (0, 1)
    release(lock_a)
    c, lock_c = reserve_instance(kind, 5, lambda i: True)
    assert c == 0
    # an instance the check refuses (ports in use) is skipped and not held
    d, lock_d = reserve_instance(kind, 5, lambda i: i != 2)
    assert d == 3
    e, lock_e = reserve_instance(kind, 5, lambda i: True)
    assert e == 2
    for fh in (lock_b, lock_c, lock_d, lock_e):
        release(fh)
