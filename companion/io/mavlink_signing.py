"""MAVLink 2 message signing on the companion's link: the key file, the checks, the counters.

Signing (mavlink.io "Message signing") appends 13 bytes to a MAVLink 2 frame: ``link_id`` (1 byte),
a 48-bit ``timestamp`` in 10 us units since 2015-01-01 00:00 UTC, and the first 6 bytes of
``SHA-256(secret_key + frame up to the timestamp)``.  It authenticates, it does not encrypt.

**Key file** (``mavlink.signing_key_file``): one line of text, either

* 64 hexadecimal characters: the 32-byte ``secret_key`` itself, byte for byte as ArduPilot's
  SETUP_SIGNING carries it (``companion signing setup --key-file F`` writes a random one, mode 0600);
* anything else: a *passphrase*, and the key is ``SHA-256(passphrase)`` -- MAVProxy's convention
  (``MAVProxy/modules/mavproxy_signing.py``, ``passphrase_to_key``: ``hashlib.sha256`` of the ASCII
  passphrase), so a vehicle set up with ``signing setup PASSPHRASE`` in MAVProxy works with a file
  holding PASSPHRASE.  Leading and trailing white space (the final newline) is not part of it; a
  non-ASCII passphrase is taken as UTF-8 (MAVProxy refuses those).

A missing, unreadable, empty, binary or all-zero key file is a :class:`SigningKeyError` (the service
does not start); a key file readable by group or others gets a warning.  The key never appears in
a log line, an exception message, the field log (its configuration copy holds the path only) or
the health report (which says ``hex`` or ``passphrase``, nothing derived from the key).

**On the link** (:class:`LinkSigning`, attached to the pymavlink connection by
:meth:`LinkSigning.attach` with pymavlink's own ``setup_signing``):

* every frame we send is signed (``link_id`` :data:`DEFAULT_LINK_ID`; the timestamp starts at the
  wall clock and never goes backwards: it follows the clock (:meth:`LinkSigning.tick`), +1 per frame,
  and the newest timestamp seen on a good incoming frame, as the MAVLink C library does);
* an incoming signed frame must verify: signature first (constant-time compare), then the replay
  check of its stream ``(link_id, system, component)``: a timestamp not newer than the stream's
  last is a replay; a new stream more than 60 s behind our timestamp is stale.  pymavlink's own
  ``check_signature`` records the stream's timestamp *before* it checks the signature, so one
  forged frame with a far-future timestamp would make every later genuine frame of that stream a
  "replay"; the check here replaces it and only a verified frame moves a stream on;
* a frame that carries a bad signature (or a replay) is dropped whatever ``signing_required`` says;
  an unsigned frame (MAVLink 1 included) is dropped when ``signing_required`` is true, accepted
  otherwise.  Every drop is counted -- ``signing: rejected unsigned``, ``signing: bad signature``,
  ``signing: replayed``, ``signing: stale stream`` -- next to ``signing: good`` and
  ``signing: accepted unsigned``, and warned about at most every :data:`WARN_INTERVAL_S`.  A
  dropped frame never reaches the link's consumers (the pipeline, the field log, the udpin peer
  lock), and it is not counted as ``bad_data`` either.

What the autopilots do (see the notes of the signing work for the sources):

* ArduPilot: SETUP_SIGNING (from MAVProxy ``signing setup``, or ``companion signing setup``) stores
  the key and activates it on every channel at once; from then on it signs everything and drops
  unsigned input except RADIO_STATUS/RADIO, and except on channel 0 (USB / SERIAL0, "assumed to
  be secure"), which accepts anything: put the companion on another port.
* PX4 v1.15 (and anything before the signing support merged in 2026, PX4-Autopilot PR #25284)
  has no signing: it ignores SETUP_SIGNING, sends unsigned frames and accepts signed ones (the C
  library skips the trailer when no key is set).  Use a key with ``signing_required = false``
  there, or none.
"""
from __future__ import annotations

import hashlib
import hmac
import logging
import os
import re
import secrets
import stat
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ..config import ConfigError

log = logging.getLogger(__name__)

KEY_BYTES = 32
SIGNING_EPOCH_UNIX_S = 1420070400            # 2015-01-01 00:00:00 UTC, the signing timestamp's zero
TIMESTAMP_UNITS_PER_S = 100_000              # 10 us units
NEW_STREAM_MAX_AGE = 60 * TIMESTAMP_UNITS_PER_S   # a new stream may be at most 1 minute behind us
DEFAULT_LINK_ID = 1                          # ours; 0 would let mavutil adopt the autopilot's link id
MAX_STREAMS = 64                             # verified (link, system, component) streams remembered
WARN_INTERVAL_S = 10.0
SIGNATURE_LEN = 6
REJECT_REASON = "Invalid signature"          # pymavlink's MAVError text for a frame refused here
_HEX_KEY = re.compile(r"[0-9a-fA-F]{64}")

COUNTER_KEYS = ("signing: good", "signing: accepted unsigned", "signing: rejected unsigned",
                "signing: bad signature", "signing: replayed", "signing: stale stream")


class SigningKeyError(ConfigError):
    """The signing key file is missing, unreadable or unusable (the message never holds the key)."""


@dataclass(frozen=True)
class SigningKey:
    key: bytes = field(repr=False)          # never in a repr, a log line or a traceback's locals summary
    kind: str                               # 'hex' or 'passphrase'
    path: str = ""


def signing_timestamp(t_unix_s: float) -> int:
    """Wall-clock time in signing units (10 us since 2015-01-01 UTC); 0 before 2015."""
    return max(0, int((t_unix_s - SIGNING_EPOCH_UNIX_S) * TIMESTAMP_UNITS_PER_S))


def key_from_text(text: str, where: str = "<key>") -> SigningKey:
    """64 hex characters = the key; any other text = a passphrase (key = its SHA-256, as MAVProxy)."""
    t = text.strip()
    if not t:
        raise SigningKeyError(f"{where}: MAVLink signing key file is empty (64 hex characters or a passphrase)")
    if _HEX_KEY.fullmatch(t):
        key, kind = bytes.fromhex(t), "hex"
    else:
        key, kind = hashlib.sha256(t.encode("utf-8")).digest(), "passphrase"
    if not any(key):
        raise SigningKeyError(f"{where}: an all-zero MAVLink signing key means 'signing off' to an autopilot")
    return SigningKey(key, kind, where)


def load_key(path: str | os.PathLike) -> SigningKey:
    """Read a key file; every failure is a :class:`SigningKeyError` naming the file, never its content."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise SigningKeyError(f"{p}: MAVLink signing key file not found "
                              f"(`companion signing setup --key-file {p}` creates one)") from None
    except PermissionError:
        raise SigningKeyError(f"{p}: MAVLink signing key file not readable (permission denied)") from None
    except IsADirectoryError:
        raise SigningKeyError(f"{p}: is a directory, not a MAVLink signing key file") from None
    except OSError as exc:
        raise SigningKeyError(f"{p}: cannot read the MAVLink signing key file: {exc.strerror or type(exc).__name__}") \
            from None
    if len(raw) > 4096:
        raise SigningKeyError(f"{p}: {len(raw)} bytes is not a MAVLink signing key file "
                              f"(one line: 64 hex characters or a passphrase)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise SigningKeyError(f"{p}: MAVLink signing key file is not text (give 64 hex characters "
                              f"or a passphrase, not a binary key)") from None
    if "\x00" in text or len(text.strip().splitlines()) > 1:
        raise SigningKeyError(f"{p}: MAVLink signing key file must hold one line "
                              f"(64 hex characters or a passphrase)")
    return key_from_text(text, str(p))


def key_file_warning(path: str | os.PathLike) -> str | None:
    """A warning when group or others may read the key file (it should be 0600)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if mode & (stat.S_IRGRP | stat.S_IROTH | stat.S_IWGRP | stat.S_IWOTH):
        return (f"{path}: MAVLink signing key file is readable or writable by other users "
                f"(mode {stat.S_IMODE(mode):04o}); chmod 600 {path}")
    return None


def generate_key_file(path: str | os.PathLike) -> bool:
    """Create ``path`` (mode 0600, never overwriting) with a random key as 64 hex characters.
    True if created, False if it already existed."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as fh:
        fh.write(secrets.token_hex(KEY_BYTES) + "\n")
    return True


def sign_encoder(mav, key: bytes, link_id: int = 0, timestamp: int | None = None):
    """Make a bare pymavlink ``MAVLink`` object (a test peer, an emulated autopilot) sign what it
    packs with ``key`` (timestamp: the wall clock unless given); returns it."""
    s = mav.signing
    s.secret_key, s.sign_outgoing, s.link_id = bytes(key), True, int(link_id) & 0xFF
    s.timestamp = signing_timestamp(time.time()) if timestamp is None else int(timestamp)
    return mav


def signing_preflight(cfg) -> str | None:
    """For a :class:`companion.config.Config`: load the key file if one is configured (raises
    :class:`SigningKeyError`), return a permission warning or None."""
    path = cfg.mavlink.signing_key_file
    if not path:
        return None
    load_key(path)
    return key_file_warning(path)


class LinkSigning:
    """Signing state of one link: attach to a pymavlink connection, count, report."""

    def __init__(self, key: SigningKey, required: bool, link_id: int = DEFAULT_LINK_ID,
                 clock: Callable[[], float] = time.time):
        if len(key.key) != KEY_BYTES:
            raise SigningKeyError(f"{key.path or '<key>'}: a MAVLink signing key has {KEY_BYTES} bytes")
        self._key = key.key
        self.kind = key.kind
        self.path = key.path
        self.required = bool(required)
        self.link_id = int(link_id) & 0xFF
        self._clock = clock
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_KEYS, 0)
        self._conn = None
        self._mav = None
        self._failure: str | None = None     # why the frame being decoded failed its signature
        self._last_warn = -float("inf")
        self._warned_counts: dict[str, int] = {}

    # -- wiring ------------------------------------------------------------------------------
    def attach(self, conn) -> None:
        """Turn signing on for a pymavlink ``mavfile`` (its ``setup_signing``), with our checks."""
        conn.setup_signing(self._key, sign_outgoing=True, allow_unsigned_callback=self._allow_unsigned,
                           initial_timestamp=signing_timestamp(self._clock()), link_id=self.link_id)
        mav = conn.mav
        mav.check_signature = self._check_signature       # instance attribute: shadows pymavlink's
        self._conn, self._mav = conn, mav
        log.info("MAVLink 2 signing on (key from %s, %s; link id %d): unsigned input %s",
                 self.path or "<key>", self.kind, self.link_id, "dropped" if self.required else "accepted")

    def tick(self) -> None:
        """Periodic: keep the outgoing timestamp at least the wall clock (pymavlink only adds 1 per
        frame), and re-attach if pymavlink replaced its MAVLink object (protocol auto-switch)."""
        conn = self._conn
        if conn is None:
            return
        if conn.mav is not self._mav:
            self.attach(conn)
        s = self._mav.signing
        now = signing_timestamp(self._clock())
        if now > s.timestamp:
            s.timestamp = now
        self._maybe_warn()

    @staticmethod
    def rejected(msg) -> bool:
        """True for the BAD_DATA pymavlink makes of a frame refused here (counted already)."""
        return str(getattr(msg, "reason", "")) == REJECT_REASON

    # -- pymavlink callbacks ---------------------------------------------------------------------
    def _check_signature(self, msgbuf, src_system: int, src_component: int) -> bool:
        s = self._mav.signing
        buf = bytes(msgbuf)
        want = hashlib.sha256(self._key + buf[:-SIGNATURE_LEN]).digest()[:SIGNATURE_LEN]
        if not hmac.compare_digest(want, buf[-SIGNATURE_LEN:]):
            return self._fail("signing: bad signature")
        link_id = buf[-13]
        lo, hi = struct.unpack_from("<IH", buf, len(buf) - 12)
        timestamp = lo | (hi << 32)
        stream = (link_id, src_system, src_component)
        last = s.stream_timestamps.get(stream)
        if last is not None:
            if timestamp <= last:
                return self._fail("signing: replayed")
        elif timestamp + NEW_STREAM_MAX_AGE < s.timestamp:
            return self._fail("signing: stale stream")
        elif len(s.stream_timestamps) >= MAX_STREAMS:
            s.stream_timestamps.pop(next(iter(s.stream_timestamps)))
        s.stream_timestamps[stream] = timestamp
        if timestamp > s.timestamp:
            s.timestamp = timestamp            # our next frames are never older than what we saw
        self._failure = None
        self.counters["signing: good"] += 1
        return True

    def _fail(self, reason: str) -> bool:
        self._failure = reason
        self.counters[reason] += 1
        return False

    def _allow_unsigned(self, mav, msg_id: int) -> bool:
        """pymavlink asks for every frame that is unsigned *or* failed its signature."""
        failure, self._failure = self._failure, None
        if failure is not None:
            return False                       # a bad signature is never waved through
        if self.required:
            self.counters["signing: rejected unsigned"] += 1
            return False
        self.counters["signing: accepted unsigned"] += 1
        return True

    # -- reporting ---------------------------------------------------------------------------
    def _maybe_warn(self) -> None:
        now = time.monotonic()
        if now - self._last_warn < WARN_INTERVAL_S:
            return
        drops = {k: v for k, v in self.counters.items()
                 if k not in ("signing: good", "signing: accepted unsigned") and v != self._warned_counts.get(k, 0)}
        if not drops:
            return
        self._last_warn = now
        self._warned_counts.update(drops)
        log.warning("MAVLink signing dropped frames: %s",
                    ", ".join(f"{k.removeprefix('signing: ')} {v}" for k, v in drops.items()))

    def health(self) -> dict:
        return {"required": self.required, "key": self.kind, "link_id": self.link_id,
                "streams": 0 if self._mav is None else len(self._mav.signing.stream_timestamps)}


def signing_from_config(mcfg) -> LinkSigning | None:
    """A :class:`LinkSigning` for a :class:`companion.config.MavlinkConfig` (None: signing off)."""
    if not mcfg.signing_key_file:
        return None
    return LinkSigning(load_key(mcfg.signing_key_file), mcfg.signing_required)


__all__ = ["LinkSigning", "SigningKey", "SigningKeyError", "load_key", "key_from_text", "key_file_warning",
           "generate_key_file", "sign_encoder", "signing_preflight", "signing_from_config", "signing_timestamp",
           "DEFAULT_LINK_ID", "KEY_BYTES", "COUNTER_KEYS"]
