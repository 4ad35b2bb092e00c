"""Logging set-up of the command line: plain lines on a terminal, syslog priorities under journald.

journald reads a service's stderr line by line and takes a leading ``<N>`` as the line's syslog
priority (sd-daemon(3), ``SyslogLevelPrefix=`` on by default), so ``journalctl -p warning`` and
the colouring work.  When stderr *is* the journal -- systemd sets ``JOURNAL_STREAM`` to its
``device:inode`` for a unit whose stdout/stderr go there; the value is compared with stderr's so
a redirected stderr (``2>file`` in a unit's script) stays plain -- every line gets the prefix of
its record's level: CRITICAL ``<2>``, ERROR ``<3>``, WARNING ``<4>``, INFO ``<6>``, DEBUG ``<7>``.
Each line of a multi-line record (a traceback) carries it, since the journal stores lines.  The
time stamp is left out there (the journal stamps every line itself).

``INVOCATION_ID`` alone does not turn it on: systemd sets it for every unit, also when stderr goes
to a file or a terminal, and every systemd that sets it (v232+) sets ``JOURNAL_STREAM`` when
stderr is the journal.
"""
from __future__ import annotations

import logging
import os
import sys
from typing import Mapping, TextIO

PLAIN_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
JOURNAL_FORMAT = "%(levelname)s %(name)s: %(message)s"


def syslog_priority(levelno: int) -> int:
    """Python level -> syslog priority (LOG_CRIT 2, LOG_ERR 3, LOG_WARNING 4, LOG_INFO 6, LOG_DEBUG 7)."""
    if levelno >= logging.CRITICAL:
        return 2
    if levelno >= logging.ERROR:
        return 3
    if levelno >= logging.WARNING:
        return 4
    if levelno >= logging.INFO:
        return 6
    return 7


def stderr_is_journal(stream: TextIO | None = None, env: Mapping[str, str] | None = None) -> bool:
    """True when ``JOURNAL_STREAM`` names this stream's device and inode (systemd.exec(5))."""
    env = os.environ if env is None else env
    value = env.get("JOURNAL_STREAM", "")
    dev, sep, ino = value.partition(":")
    if not sep:
        return False
    stream = sys.stderr if stream is None else stream
    try:
        st = os.fstat(stream.fileno())
        return (int(dev), int(ino)) == (st.st_dev, st.st_ino)
    except (AttributeError, OSError, ValueError):     # no fd (a test's StringIO), closed, bad value
        return False


class SyslogPrefixFormatter(logging.Formatter):
    """Prefix every line of a formatted record with ``<N>``, N its syslog priority."""

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).split("\n"))


def configure_logging(level: int, stream: TextIO | None = None, env: Mapping[str, str] | None = None) -> bool:
    """``logging.basicConfig`` on stderr (or ``stream``), with priority prefixes when it is the
    journal.  Returns whether the prefixes are on."""
    stream = sys.stderr if stream is None else stream
    journal = stderr_is_journal(stream, env)
    handler = logging.StreamHandler(stream)
    handler.setFormatter(SyslogPrefixFormatter(JOURNAL_FORMAT) if journal else logging.Formatter(PLAIN_FORMAT))
    logging.basicConfig(level=level, handlers=[handler])
    return journal


__all__ = ["configure_logging", "stderr_is_journal", "syslog_priority", "SyslogPrefixFormatter"]
