"""A simulated receiver's byte streams, as real receivers write them (test helper)."""
from __future__ import annotations


def ubx_epochs(sim, scenario, t_end_gps: float, leap_s: int) -> list[tuple[float, bytes]]:
    """(epoch GPS time, UBX bytes) per rover epoch up to ``t_end_gps``: its RXM-RAWX
    (sitl.autopilot) and the RXM-SFRBX subframes due then (sitl.lnav_encode: the ephemerides and
    the scenario's Klobuchar page), as a u-blox with raw output sends them."""
    from sitl.autopilot import rawx_frame
    from sitl.lnav_encode import ephemeris_subframe, klobuchar_subframe, quantised, sfrbx_frame, subframe_due
    ephs = {e.sat: quantised(e) for e in sim.ephemerides}
    out = []
    for ep in sim.rover_epochs:
        if ep.t_gps > t_end_gps:
            break
        ubx = bytearray(rawx_frame(ep, leap_s))
        due = subframe_due(ep.t_gps)
        if due is not None and due[0] != 5:
            for ch, o in enumerate(ep.observations):
                if o.sat in ephs and o.signal == "L1C":
                    words = (klobuchar_subframe(scenario.klobuchar_alpha, scenario.klobuchar_beta, due[1])
                             if due[0] == 4 else ephemeris_subframe(ephs[o.sat], due[0], due[1]))
                    ubx += sfrbx_frame(int(o.sat[1:]), words, channel=ch)
        out.append((ep.t_gps, bytes(ubx)))
    return out
