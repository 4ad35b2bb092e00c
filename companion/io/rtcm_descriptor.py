"""RTCM 1007 / 1008 / 1033: what the base says it is (antenna, receiver, firmware, serial numbers).

A field team wants to see which base it is connected to, and the post-processing RTK decides
GLONASS's integers from the two receivers' models (:func:`companion.gnss.rtk_post.glonass_ar_of`):
two of one model cancel their inter-channel biases.  1007 carries the antenna descriptor and
setup ID, 1008 adds the antenna serial number, 1033 adds the receiver type, firmware and receiver
serial (DF227-DF232).  A u-blox base sends none of them.

The strings come from the caster and are shown to people (health report, status page, terminal):
only printable ASCII is kept, at most 31 characters each (the standard's own limit, DF029), so a
hostile descriptor cannot carry control sequences into a terminal or a page.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

#: the standard's longest descriptor (DF029 / DF032 / DF227 / DF229 / DF231 are 8-bit counts, each
#: string defined up to 31 characters)
MAX_DESCRIPTOR_CHARS = 31


@dataclass(frozen=True)
class BaseDescriptor:
    station_id: int
    antenna: str = ""               # IGS antenna + radome names, e.g. 'JAVGRANT_G5T NONE'
    antenna_setup_id: int = 0
    antenna_serial: str = ""
    receiver: str = ""              # e.g. 'NOV OEM729' (1033 only)
    firmware: str = ""
    receiver_serial: str = ""
    message: int = 0                # the message it came from: 1007, 1008 or 1033

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        parts = [f"station {self.station_id}"]
        if self.receiver:
            parts.append(f"receiver {self.receiver}" + (f" (firmware {self.firmware})" if self.firmware else ""))
        if self.antenna:
            parts.append(f"antenna {self.antenna}")
        return ", ".join(parts) + f" (RTCM {self.message})"


def _text(msg, field: str, count_field: str) -> str:
    """A character array of pyrtcm's ``DFxxx_01`` ... fields, printable ASCII only."""
    n = min(int(getattr(msg, count_field, 0) or 0), MAX_DESCRIPTOR_CHARS)
    chars = (getattr(msg, f"{field}_{i:02d}", "") for i in range(1, n + 1))
    return "".join(c for c in "".join(str(c) for c in chars) if " " <= c <= "~").strip()


def base_descriptor(mtype: int, msg) -> BaseDescriptor:
    """The descriptor of a parsed 1007, 1008 or 1033 (pyrtcm's fields)."""
    return BaseDescriptor(
        station_id=int(msg.DF003),
        antenna=_text(msg, "DF030", "DF029"),
        antenna_setup_id=int(getattr(msg, "DF031", 0) or 0),
        antenna_serial=_text(msg, "DF033", "DF032") if mtype in (1008, 1033) else "",
        receiver=_text(msg, "DF228", "DF227") if mtype == 1033 else "",
        firmware=_text(msg, "DF230", "DF229") if mtype == 1033 else "",
        receiver_serial=_text(msg, "DF232", "DF231") if mtype == 1033 else "",
        message=mtype)


def merged(old: BaseDescriptor | None, new: BaseDescriptor) -> BaseDescriptor:
    """``new``, keeping what only a fuller message of the same station said (a caster that sends
    1033 now and then and 1007 in between keeps its receiver type)."""
    if old is None or old.station_id != new.station_id or new.message == 1033:
        return new
    keep = {k: getattr(old, k) for k in ("receiver", "firmware", "receiver_serial") if not getattr(new, k)}
    if new.message == 1007 and old.antenna == new.antenna:
        keep["antenna_serial"] = old.antenna_serial
    return BaseDescriptor(**{**asdict(new), **keep, "message": old.message if keep.get("receiver") else new.message})


__all__ = ["BaseDescriptor", "MAX_DESCRIPTOR_CHARS", "base_descriptor", "merged"]
