"""The EKF origin of our local NED outputs: proposed, sent, read back, confirmed or adopted.

VISION_POSITION_ESTIMATE and ODOMETRY carry NED metres about the autopilot's EKF origin.  If our
origin and the autopilot's differ, every position we send lands offset by the difference, and
nothing in the data shows it.  So the origin is read back, not assumed:

* **Request** GPS_GLOBAL_ORIGIN (MAV_CMD_REQUEST_MESSAGE, id 49) from link-up, every
  :data:`REQUEST_INTERVAL_S` until the autopilot has answered, then every
  :data:`CHECK_INTERVAL_S`.  ArduPilot answers only once it has an origin (the command is
  ACCEPTED either way) and also sends it, on the channel that asked, when our
  SET_GPS_GLOBAL_ORIGIN is accepted.  PX4 v1.15 (``GPS_GLOBAL_ORIGIN.hpp``) answers a request
  while its local position has a global reference and streams it when the reference changes.
* **Propose** ours at the first injectable solution: rounded to what the message carries,
  1e-7 deg, and the altitude to whole **centimetres** -- ArduPilot stores ``altitude / 10``
  (integer cm, ``GCS_MAVLINK::handle_set_gps_global_origin``), so a mm value would come back up
  to 9 mm different.  SET_GPS_GLOBAL_ORIGIN is sent at :data:`ORIGIN_REPEAT_S` (UDP) and every
  :data:`RESEND_INTERVAL_S` after, until the read-back confirms it; never once confirmed.
* **Confirmed** = the autopilot reports our latitude and longitude exactly and the altitude
  within 1 cm: the outputs then use the autopilot's values, bit for bit.
* **A different origin** (ArduPilot's EKF3 sets its own from its GPS ~10 s after the first good
  fix and then ignores ours -- measured on ArduCopter 4.7.0-dev SITL with EK3_SRC1_POSXY 6; or a
  ground station set one): **adopted**.  Decision and why: the filter runs in ECEF, the origin is
  only the reference point of the final ECEF -> NED conversion (done exactly the way ArduPilot
  converts back, :func:`~companion.io.mavlink_encode.ardupilot_ned_from_origin`), so expressing our
  positions about the autopilot's origin puts them where they are meant to be in its frame
  while leaving the estimate itself untouched.  Refusing to send would ground a vehicle whose
  autopilot cannot be told another origin (ArduPilot keeps the first one until it reboots) for
  no gain.  The difference is reported (``mismatch_m``, STATUSTEXT).  It is unsafe only when
  the autopilot's origin is far away (float32 EKF states, a local level frame tilted from the
  vehicle's): beyond :data:`MAX_ADOPT_M` vision/odometry are **refused** (STATUSTEXT, counter)
  until it changes (an autopilot reboot).
* An origin that changes after estimates went out (PX4 resetting its reference, a reboot with a
  new one) is adopted too and bumps :attr:`OriginManager.epoch`, which the service adds to the
  estimates' ``reset_counter`` so the autopilot takes the step as a reset, not a glitch.
* **Waiting**: estimates are held until the origin is known (confirmed or adopted), at most
  :data:`CONFIRM_WAIT_S` after our proposal; then an autopilot that never answers gets them
  with our own origin (counted, one STATUSTEXT) -- as before the read-back existed.
* After an autopilot reboot its origin is gone: ours (unchanged, so our frame stays put) is
  sent again and read back again.

Pure logic: it returns the messages to send (:meth:`OriginManager.tick`); the service sends them.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from ..nav.earth import geodetic_to_ecef

ORIGIN_REPEAT_S = (0.0, 1.0, 2.0, 3.0, 5.0, 10.0)   # after the proposal: UDP may drop one
RESEND_INTERVAL_S = 10.0         # then, until confirmed
REQUEST_INTERVAL_S = 1.0         # GPS_GLOBAL_ORIGIN requests until the autopilot answered
CHECK_INTERVAL_S = 10.0          # ... then (an origin that changes is noticed)
CONFIRM_WAIT_S = 3.0             # estimates held this long at most for the read-back
MAX_ADOPT_M = 50_000.0           # an autopilot origin further than this is not used
ALT_TOLERANCE_MM = 10            # ArduPilot keeps whole centimetres
MSG_ID_GPS_GLOBAL_ORIGIN = 49
MAV_SEVERITY_ERROR, MAV_SEVERITY_WARNING, MAV_SEVERITY_INFO = 3, 4, 6

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class OriginE7:
    """An origin as MAVLink carries it: 1e-7 deg, 1e-7 deg, mm (AMSL)."""
    lat_e7: int
    lon_e7: int
    alt_mm: int

    @classmethod
    def from_origin(cls, o) -> "OriginE7":
        """From a :class:`~companion.io.mavlink_encode.Origin`: lat/lon rounded to 1e-7 deg, altitude to cm."""
        return cls(o.lat_e7(), o.lon_e7(), 10 * round(o.alt_m * 100.0))

    @classmethod
    def from_message(cls, msg) -> "OriginE7":
        return cls(int(msg.latitude), int(msg.longitude), int(msg.altitude))

    def to_origin(self):
        from .mavlink_encode import Origin
        return Origin(math.radians(self.lat_e7 * 1e-7), math.radians(self.lon_e7 * 1e-7), self.alt_mm * 1e-3)

    def distance_m(self, other: "OriginE7") -> float:
        """Straight-line distance (the common geoid offset cancels)."""
        a = geodetic_to_ecef(math.radians(self.lat_e7 * 1e-7), math.radians(self.lon_e7 * 1e-7), self.alt_mm * 1e-3)
        b = geodetic_to_ecef(math.radians(other.lat_e7 * 1e-7), math.radians(other.lon_e7 * 1e-7),
                             other.alt_mm * 1e-3)
        return float(math.dist(a, b))

    def matches(self, other: "OriginE7") -> bool:
        return (self.lat_e7 == other.lat_e7 and self.lon_e7 == other.lon_e7
                and abs(self.alt_mm - other.alt_mm) < ALT_TOLERANCE_MM)

    def as_dict(self) -> dict:
        return {"lat_e7": self.lat_e7, "lon_e7": self.lon_e7, "alt_mm": self.alt_mm}


def command_request_message(msg_id: int, target_system: int = 1, target_component: int = 1):
    """COMMAND_LONG MAV_CMD_REQUEST_MESSAGE (param1 = message id)."""
    from .mavlink_codec import ENCODER, m
    return ENCODER.command_long_encode(int(target_system), int(target_component), m.MAV_CMD_REQUEST_MESSAGE, 0,
                                    float(msg_id), 0, 0, 0, 0, 0, 0)


class OriginManager:
    """Which origin our NED outputs use (see the module doc).  ``now`` is a monotonic clock (s)."""

    def __init__(self, *, send_set: bool = True, target_system: int = 1, target_component: int = 1):
        self.send_set = send_set
        self.target_system = target_system
        self.target_component = target_component
        self.ours: OriginE7 | None = None          # proposed from our first injectable position
        self.autopilot: OriginE7 | None = None     # the last GPS_GLOBAL_ORIGIN
        self.used: OriginE7 | None = None          # what the outputs use once decided
        self.confirmed = False
        self.refused = False
        self.mismatch_m: float | None = None
        self.epoch = 0                             # origin changes after estimates were sent
        self.sent_with_used = False
        self.counters: dict[str, int] = {}
        self.events: list[tuple[int, str]] = []
        self._t_proposed: float | None = None
        self._repeats_done: set[int] = set()
        self._last_set: float = -math.inf
        self._last_request: float = -math.inf
        self._unconfirmed_announced = False

    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    def _event(self, severity: int, text: str) -> None:
        self.events.append((severity, text))
        (log.warning if severity <= MAV_SEVERITY_WARNING else log.info)("%s", text)

    def drain_events(self) -> list[tuple[int, str]]:
        ev, self.events = self.events, []
        return ev

    # -- inputs ------------------------------------------------------------------------------
    def on_gps_global_origin(self, msg, now: float) -> None:
        if msg.get_srcSystem() != self.target_system:
            return
        self._count("GPS_GLOBAL_ORIGIN received")
        o = OriginE7.from_message(msg)
        if o != self.autopilot:
            self.autopilot = o
            self._decide(now)

    def propose(self, origin, now: float) -> None:
        """Our origin (a :class:`~companion.io.mavlink_encode.Origin`) at the first injectable solution."""
        if self.ours is not None:
            return
        self.ours = OriginE7.from_origin(origin)
        self._t_proposed = now
        self._repeats_done.clear()
        self._decide(now)

    def on_autopilot_reboot(self, now: float) -> None:
        """Its origin is gone: ours goes out again (our frame stays where it was)."""
        self._count("autopilot reboots")
        self.autopilot = None
        self.confirmed = self.refused = False
        if self.ours is not None:
            self._t_proposed = now
            self._repeats_done.clear()
            self._last_set = -math.inf
        self._last_request = -math.inf

    # -- decision ----------------------------------------------------------------------------
    def _use(self, o: OriginE7) -> None:
        if self.used is not None and self.sent_with_used and o.distance_m(self.used) >= 0.01:
            self.epoch += 1
            self._count("origin changes after estimates were sent")
        if o != self.used:
            self.sent_with_used = False
        self.used = o

    def _decide(self, now: float) -> None:
        ap, ours = self.autopilot, self.ours
        if ap is None or ours is None:
            return
        self.mismatch_m = round(ap.distance_m(ours), 3)
        if ap.matches(ours):
            self.refused = False
            self.confirmed = True
            self._use(ap)
            self._count("origin confirmed")
            self._event(MAV_SEVERITY_INFO, "origin confirmed by autopilot")
        elif self.mismatch_m > MAX_ADOPT_M:
            self.confirmed = False
            self.refused = True
            self._count("origin refused: autopilot origin too far")
            self._event(MAV_SEVERITY_ERROR, f"AP origin {self.mismatch_m / 1000:.0f} km off: no ext nav")
        else:
            self.refused = False
            self.confirmed = True
            self._use(ap)
            self._count("origin adopted from autopilot")
            self._event(MAV_SEVERITY_WARNING, f"AP origin {self.mismatch_m:.2f} m from ours: adopted")

    # -- outputs -----------------------------------------------------------------------------
    def output_origin(self, now: float):
        """The :class:`~companion.io.mavlink_encode.Origin` to send estimates about, or None = hold them."""
        if self.refused or self.ours is None:
            return None
        if self.confirmed and self.used is not None:
            return self.used.to_origin()
        if self._t_proposed is not None and now - self._t_proposed >= CONFIRM_WAIT_S:
            if not self._unconfirmed_announced:
                self._unconfirmed_announced = True
                self._event(MAV_SEVERITY_WARNING, "origin not confirmed by autopilot")
            self._use(self.ours)
            return self.ours.to_origin()
        return None

    def mark_sent(self) -> None:
        self.sent_with_used = True

    def tick(self, now: float, link_up: bool = True) -> list:
        """The messages due now: SET_GPS_GLOBAL_ORIGIN repeats (until confirmed) and
        GPS_GLOBAL_ORIGIN requests."""
        if not link_up:
            return []
        out = []
        if self.send_set and self.ours is not None and not self.confirmed and not self.refused:
            dt = now - self._t_proposed
            due = any(dt >= t and i not in self._repeats_done for i, t in enumerate(ORIGIN_REPEAT_S))
            if due or (dt > ORIGIN_REPEAT_S[-1] and now - self._last_set >= RESEND_INTERVAL_S):
                self._repeats_done.update(i for i, t in enumerate(ORIGIN_REPEAT_S) if dt >= t)
                self._last_set = now
                from .mavlink_encode import set_gps_global_origin
                o = self.ours
                out.append(set_gps_global_origin(o.lat_e7 * 1e-7, o.lon_e7 * 1e-7, o.alt_mm * 1e-3,
                                                 self.target_system))
                self._count("sent SET_GPS_GLOBAL_ORIGIN")
        interval = CHECK_INTERVAL_S if self.autopilot is not None else REQUEST_INTERVAL_S
        if out or now - self._last_request >= interval:
            # with every SET too: the answer of an autopilot that already had one is the read-back
            self._last_request = now
            out.append(command_request_message(MSG_ID_GPS_GLOBAL_ORIGIN, self.target_system,
                                               self.target_component))
            self._count("sent REQUEST_MESSAGE GPS_GLOBAL_ORIGIN")
        return out

    def health(self) -> dict:
        return {"confirmed": self.confirmed, "mismatch_m": self.mismatch_m, "refused": self.refused,
                "source": None if self.used is None else ("autopilot" if self.confirmed else "companion (unconfirmed)"),
                "used": None if self.used is None else self.used.as_dict(),
                "ours": None if self.ours is None else self.ours.as_dict(),
                "autopilot": None if self.autopilot is None else self.autopilot.as_dict(),
                "epoch": self.epoch, **self.counters}


__all__ = ["OriginE7", "OriginManager", "command_request_message", "ORIGIN_REPEAT_S", "CONFIRM_WAIT_S",
           "MAX_ADOPT_M", "MSG_ID_GPS_GLOBAL_ORIGIN"]
