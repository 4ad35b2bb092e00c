"""The harness's caster must not be an open door (issue 14)."""
from __future__ import annotations

import asyncio

from sitl.caster import MiniNtripCaster, start_caster


def test_mini_caster_listens_on_loopback_only_with_a_fresh_password():
    async def main():
        src = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
        port = src.sockets[0].getsockname()[1]
        a = await start_caster(port, prefer_str2str=False)
        b = await start_caster(port, prefer_str2str=False)
        try:
            addrs = [s.getsockname()[0] for s in a.mini._server.sockets]
            return addrs, a.password, b.password
        finally:
            await a.close()
            await b.close()
            src.close()
    addrs, pa, pb = asyncio.run(main())
    assert addrs == ["127.0.0.1"]
    assert pa != pb and len(pa) >= 16 and pa != "sitl"


def test_mini_caster_default_host_is_loopback():
    m = MiniNtripCaster("127.0.0.1", 1, "M")
    assert m.host == "127.0.0.1"
