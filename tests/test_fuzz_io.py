"""Bounded fuzzing of the untrusted-input entry points (issue 14): a few thousand seeded random,
mutated and well-formed-but-random inputs per entry point, seconds in all.  The contract: never
raise anything but the documented error, count what is dropped, keep buffers bounded, do bounded
work per byte.  The inputs and the checks live in ``tests/fuzz_targets.py``; ``python -m tests.fuzz``
runs the same targets a million times."""
from __future__ import annotations

import logging
import random
import zlib

import pytest

from tests.fuzz_targets import TARGETS

# inputs per target in CI: a few thousand, fewer where one input costs milliseconds
CI_INPUTS = {"ubx": 2000, "rtcm": 2000, "mavlink": 1000, "ntrip_head": 3000, "ntrip_chunked": 3000,
             "fieldlog": 1500, "config": 1000}


@pytest.fixture(autouse=True)
def _quiet():
    logging.disable(logging.WARNING)
    yield
    logging.disable(logging.NOTSET)


def test_every_target_has_a_ci_budget():
    assert set(CI_INPUTS) == set(TARGETS)


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_fuzz_target_keeps_its_contract(name):
    target = TARGETS[name]
    rng = random.Random(zlib.crc32(name.encode()))
    for _ in range(CI_INPUTS[name]):
        target.run(target.generate(rng))


# ------------------------------------------------------------- cases found by `python -m tests.fuzz`
def test_regression_config_string_with_a_newline_writes_back_as_valid_toml(tmp_path):
    # seed 1, config input 162: a multi-line string value was written back with a raw newline,
    # so the configuration copy in every field log was unreadable TOML
    from companion.config import load_config, loads_config
    p = tmp_path / "c.toml"
    p.write_text("[corrections.ntrip]\nmountpoint = '''multi\nline'''\nuser = \"tab\\there\\u0001\"\n")
    cfg = load_config(p)
    assert cfg.corrections.ntrip.mountpoint == "multi\nline"
    assert loads_config(cfg.to_toml(comments=False)) == cfg
