"""Log lines carry sd-daemon ``<N>`` syslog priorities when stderr is the journal (JOURNAL_STREAM
names stderr's device:inode), and are plain otherwise.  The subprocess tests run the real command
line with stderr on a real file whose device and inode stand in for journald's stream."""
from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

from companion.journal_log import SyslogPrefixFormatter, stderr_is_journal, syslog_priority

REPO = Path(__file__).resolve().parents[1]

SCRIPT = """
import logging
from companion.journal_log import configure_logging
configure_logging(logging.DEBUG)
log = logging.getLogger("companion.test")
log.debug("d"); log.info("i"); log.warning("w"); log.error("e"); log.critical("c")
try:
    1 / 0
except ZeroDivisionError:
    log.exception("boom")
"""


def _run(tmp_path, env_extra: dict, journal_matches_file: bool) -> list[str]:
    err = tmp_path / "stderr.txt"
    err.write_text("")
    env = {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM", "INVOCATION_ID")}
    env["PYTHONPATH"] = str(REPO)
    if journal_matches_file:
        st = err.stat()
        env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}"
    env.update(env_extra)
    with err.open("w") as fh:
        subprocess.run([sys.executable, "-c", SCRIPT], stderr=fh, env=env, check=True, timeout=60)
    return err.read_text().splitlines()


def test_priorities_when_stderr_is_the_journal(tmp_path):
    lines = _run(tmp_path, {"INVOCATION_ID": "abc"}, journal_matches_file=True)
    assert lines[:5] == ["<7>DEBUG companion.test: d", "<6>INFO companion.test: i", "<4>WARNING companion.test: w",
                         "<3>ERROR companion.test: e", "<2>CRITICAL companion.test: c"]
    tb = lines[5:]
    assert tb[0] == "<3>ERROR companion.test: boom" and len(tb) >= 4
    assert all(line.startswith("<3>") for line in tb)              # every traceback line: the journal's unit
    assert tb[-1] == "<3>ZeroDivisionError: division by zero"


def test_plain_lines_otherwise(tmp_path):
    for extra, matches in (({}, False), ({"JOURNAL_STREAM": "1:2"}, False), ({"INVOCATION_ID": "abc"}, False)):
        lines = _run(tmp_path, extra, journal_matches_file=matches)
        assert lines and not any(line.startswith("<") for line in lines), extra
        assert " WARNING companion.test: w" in lines[2]                   # with its time stamp


def test_stderr_is_journal_and_the_level_map(tmp_path):
    f = (tmp_path / "x").open("w")
    st = os.fstat(f.fileno())
    assert stderr_is_journal(f, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
    assert not stderr_is_journal(f, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"})
    assert not stderr_is_journal(f, {"JOURNAL_STREAM": "garbage"}) and not stderr_is_journal(f, {})
    f.close()
    assert [syslog_priority(n) for n in (5, 10, 15, 20, 25, 30, 40, 50, 60)] == [7, 7, 7, 6, 6, 4, 3, 2, 2]
    rec = logging.LogRecord("n", logging.WARNING, __file__, 1, "two\nlines", None, None)
    assert SyslogPrefixFormatter("%(message)s").format(rec) == "<4>two\n<4>lines"
