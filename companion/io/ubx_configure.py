"""``companion gnss configure``: switch a u-blox receiver's raw output on (RXM-RAWX, RXM-SFRBX).

A factory-default u-blox emits NMEA and NAV messages only; the tightly coupled filter needs
RXM-RAWX (pseudorange, carrier phase, Doppler) and RXM-SFRBX (broadcast ephemerides).  This module
builds the configuration frames with pyubx2, sends them one at a time and reads each answer back:

* **F9 generation** (ZED-F9P/F9R/F9T, NEO-M9N ...; protocol 27+): one UBX-CFG-VALSET per key, so an
  ACK-ACK / ACK-NAK belongs to exactly one key (a VALSET with several keys is accepted or
  rejected as a whole, and a NAK would not say which key).  Keys: ``CFG_<PORT>OUTPROT_UBX``,
  ``CFG_MSGOUT_UBX_RXM_RAWX_<PORT>``, ``CFG_MSGOUT_UBX_RXM_SFRBX_<PORT>``, ``CFG_RATE_MEAS``,
  ``CFG_RATE_NAV``, optionally ``CFG_MSGOUT_UBX_NAV_RELPOSNED_<PORT>`` (moving-base rover) and
  ``CFG_SIGNAL_<SYS>_ENA`` (constellations; the receiver restarts its GNSS subsystem then).
  Layers: RAM, battery-backed RAM, flash (``--layers``).
* **M8 generation** (NEO-M8T/M8P, protocol < 27): legacy UBX-CFG-MSG in its 3-byte form (the rate
  on the port the command arrives on: the port the companion reads) and UBX-CFG-RATE; with a
  persistent layer, UBX-CFG-CFG saves the whole configuration to BBR and/or flash.

Both generations acknowledge every CFG message with ACK-ACK or ACK-NAK (class 0x05) carrying the
class and id it answers; as the frames go out one by one, an answer is matched to the one frame
in flight.  A missing answer stops the run (no receiver, wrong port or baud rate); a NAK is
reported by key and the others are still sent.

Transports: a serial device (pyserial), ``tcp://HOST:PORT`` (a receiver behind a serial-to-TCP
bridge, ser2net / u-center's server), ``udp://HOST:PORT``, or the autopilot's GPS port through
MAVLink SERIAL_CONTROL (``--mavlink``, ArduPilot; :class:`TunnelTransport`).
"""
from __future__ import annotations

import socket
import time
from collections import Counter
from dataclasses import dataclass

from ..extras import require

# companion.io.ubx (numpy) is imported where it is used: building the `companion` parser must stay light

UBX_SYNC = b"\xb5\x62"
ACK_CLASS, ACK_ACK, ACK_NAK = 0x05, 0x01, 0x00
#: receiver port name -> (VALSET key fragment of the message outputs, of the output protocol)
F9_PORTS = {"uart1": ("UART1", "UART1"), "uart2": ("UART2", "UART2"), "usb": ("USB", "USB"),
            "i2c": ("I2C", "I2C"), "spi": ("SPI", "SPI")}
#: --systems letter -> CFG_SIGNAL_<name>_ENA
F9_SYSTEMS = {"G": "GPS", "E": "GAL", "C": "BDS", "J": "QZSS", "R": "GLO"}
LAYER_BITS = {"ram": 0x01, "bbr": 0x02, "flash": 0x04}
M8_SAVE_ALL = b"\x1f\x1f\x00\x00"        # CFG-CFG saveMask: ioPort msgConf infMsg navConf rxmConf senConf ...
MIN_RATE_HZ, MAX_RATE_HZ = 0.1, 25.0     # F9P raw output tops out at 25 Hz (20 Hz with RTK)
UART_BAUDS = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
# What raw output costs on a UART (for the warning, not a limit): RXM-RAWX is 16 + 32 bytes per
# signal (+8 framing); a multi-constellation dual-frequency F9P tracks about 60 signals, a
# single-frequency M8T about 25; SFRBX, NAV and NMEA add about 1500 B/s between them.
RAWX_SIGNALS_TYPICAL = {"f9": 60, "m8": 25}
OTHER_OUTPUT_BPS = 1500.0


class ReceiverConfigError(Exception):
    """A user-facing error: bad options, or the receiver did not accept / did not answer."""


@dataclass(frozen=True)
class ConfigItem:
    """One setting and the UBX frame that carries it."""
    key: str          # VALSET key name, or the legacy message and what it sets
    value: object
    frame: bytes

    @property
    def cfg_class_id(self) -> tuple[int, int]:
        return self.frame[2], self.frame[3]


@dataclass
class ItemResult:
    item: ConfigItem
    status: str       # "ack", "nak", "timeout", "not sent"
    seconds: float = 0.0


def _pyubx2():
    return require("pyubx2", "receiver", "companion gnss configure")


def layers_mask(layers: str) -> int:
    names = [x.strip().lower() for x in layers.split(",") if x.strip()]
    bad = [x for x in names if x not in LAYER_BITS]
    if bad or not names:
        raise ReceiverConfigError(f"--layers: comma-separated {', '.join(LAYER_BITS)}; got {layers!r}")
    mask = 0
    for x in names:
        mask |= LAYER_BITS[x]
    return mask


def raw_output_bytes_per_s(generation: str, rate_hz: float) -> float:
    """Rough UBX output of a receiver configured this way (bytes/s)."""
    return rate_hz * (16 + 32 * RAWX_SIGNALS_TYPICAL[generation] + 8) + OTHER_OUTPUT_BPS


def bandwidth_warning(generation: str, rate_hz: float, baud: int) -> str | None:
    """A warning when the raw output would not fit a UART at ``baud`` (8N1: 10 bits a byte)."""
    need, have = raw_output_bytes_per_s(generation, rate_hz), baud / 10.0
    if need <= 0.8 * have:
        return None
    return (f"at {rate_hz:g} Hz the raw output is about {need:.0f} B/s, more than 80 % of what "
            f"{baud} baud carries ({have:.0f} B/s): frames will be lost; raise the baud rate "
            "(--receiver-baud, then --baud) or lower --rate-hz")


def _measurement_period_ms(rate_hz: float) -> int:
    if not MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        raise ReceiverConfigError(f"--rate-hz must be within {MIN_RATE_HZ:g}-{MAX_RATE_HZ:g} Hz, got {rate_hz:g}")
    return int(round(1000.0 / rate_hz))


def f9_items(*, receiver_port: str = "uart1", rate_hz: float = 5.0, moving_base: bool = False,
             systems: str | None = None, layers: str = "ram,bbr,flash",
             receiver_baud: int | None = None) -> list[ConfigItem]:
    """The CFG-VALSET frames (one key each) for an F9-generation receiver; a new baud rate goes
    last (the receiver switches at once, its ACK may be lost on the way)."""
    ubx = _pyubx2()
    if receiver_port not in F9_PORTS:
        raise ReceiverConfigError(f"--receiver-port: one of {', '.join(F9_PORTS)}; got {receiver_port!r}")
    msg_port, prot_port = F9_PORTS[receiver_port]
    keys: list[tuple[str, object]] = [
        (f"CFG_{prot_port}OUTPROT_UBX", 1),                 # UBX output on that port (default on, but make sure)
        (f"CFG_MSGOUT_UBX_RXM_RAWX_{msg_port}", 1),         # every measurement epoch
        (f"CFG_MSGOUT_UBX_RXM_SFRBX_{msg_port}", 1),        # every subframe as it is decoded
        ("CFG_RATE_MEAS", _measurement_period_ms(rate_hz)),
        ("CFG_RATE_NAV", 1),                                 # a navigation solution per measurement
    ]
    if moving_base:
        keys.append((f"CFG_MSGOUT_UBX_NAV_RELPOSNED_{msg_port}", 1))
    if systems:
        wanted = {s.strip().upper() for s in systems.split(",") if s.strip()}
        bad = wanted - set(F9_SYSTEMS)
        if bad or not wanted:
            raise ReceiverConfigError(f"--systems: comma-separated {','.join(F9_SYSTEMS)}; got {systems!r}")
        keys += [(f"CFG_SIGNAL_{name}_ENA", int(letter in wanted)) for letter, name in F9_SYSTEMS.items()]
    if receiver_baud:
        if receiver_port not in ("uart1", "uart2"):
            raise ReceiverConfigError("--receiver-baud is for --receiver-port uart1 or uart2")
        if receiver_baud not in UART_BAUDS:
            raise ReceiverConfigError(f"--receiver-baud: one of {', '.join(map(str, UART_BAUDS))}")
        keys.append((f"CFG_{msg_port}_BAUDRATE", int(receiver_baud)))
    mask = layers_mask(layers)
    return [ConfigItem(k, v, ubx.UBXMessage.config_set(mask, 0, [(k, v)]).serialize()) for k, v in keys]


def m8_items(*, rate_hz: float = 5.0, moving_base: bool = False, layers: str = "ram") -> list[ConfigItem]:
    """CFG-MSG (current port), CFG-RATE and, for a persistent layer, CFG-CFG, for an M8 receiver."""
    ubx = _pyubx2()
    mask = layers_mask(layers)

    def cfg_msg(name: str, cls: int, mid: int) -> ConfigItem:
        # 3-byte form: the rate on the port this frame arrives on, the other ports untouched
        return ConfigItem(f"CFG-MSG {name} (this port)", 1,
                          ubx.UBXMessage(b"\x06", b"\x01", ubx.SET, payload=bytes([cls, mid, 1])).serialize())

    items = [cfg_msg("RXM-RAWX", 0x02, 0x15), cfg_msg("RXM-SFRBX", 0x02, 0x13)]
    if moving_base:
        items.append(cfg_msg("NAV-RELPOSNED", 0x01, 0x3C))     # M8P only
    period = _measurement_period_ms(rate_hz)
    items.append(ConfigItem("CFG-RATE measRate_ms", period,
                            ubx.UBXMessage("CFG", "CFG-RATE", ubx.SET, measRate=period, navRate=1,
                                           timeRef=1).serialize()))
    if mask & (LAYER_BITS["bbr"] | LAYER_BITS["flash"]):
        bbr, flash = int(bool(mask & LAYER_BITS["bbr"])), int(bool(mask & LAYER_BITS["flash"]))
        where = "+".join(n for n, on in (("bbr", bbr), ("flash", flash)) if on)
        items.append(ConfigItem(f"CFG-CFG save ({where})", 1,
                                ubx.UBXMessage("CFG", "CFG-CFG", ubx.SET, saveMask=M8_SAVE_ALL, devBBR=bbr,
                                               devFlash=flash).serialize()))
    return items


# ----------------------------------------------------------------------------------------- I/O
class UdpTransport:
    """A receiver (or bridge) at a UDP address: datagrams out, whatever comes back in."""

    def __init__(self, host: str, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect((host, port))

    def write(self, data: bytes) -> None:
        self.sock.send(data)

    def read_some(self, timeout_s: float) -> bytes:
        self.sock.settimeout(max(timeout_s, 1e-3))
        try:
            return self.sock.recv(65536)
        except (socket.timeout, ConnectionRefusedError):
            return b""

    def close(self) -> None:
        self.sock.close()


class SerialTransport:
    """A pyserial port: a device path, or ``socket://HOST:PORT`` (pyserial's TCP URL handler)."""

    def __init__(self, url: str, baud: int):
        import serial                                   # pyserial: a core dependency
        try:
            self.port = serial.serial_for_url(url, baudrate=baud, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ReceiverConfigError(f"cannot open {url}: {exc}") from exc

    def write(self, data: bytes) -> None:
        self.port.write(data)
        self.port.flush()

    def read_some(self, timeout_s: float) -> bytes:
        self.port.timeout = max(timeout_s, 1e-3)
        return self.port.read(max(1, self.port.in_waiting))

    def close(self) -> None:
        self.port.close()


class TunnelTransport:
    """The receiver on the autopilot's GPS port, through MAVLink SERIAL_CONTROL
    (:class:`~companion.io.serial_control.SerialControlTunnel`, ArduPilot only).

    The link and the tunnel run on an asyncio loop in a background thread; :meth:`write` and
    :meth:`read_some` are called from the (synchronous) configuration run.  The port is locked
    (EXCLUSIVE polls) from the first HEARTBEAT until :meth:`close`, which unlocks it three times
    (one lost datagram must not leave the autopilot without its GPS)."""

    def __init__(self, connection: str, device: str = "GPS1", *, baud: int = 0, target_system: int = 1,
                 heartbeat_timeout_s: float = 5.0):
        import asyncio
        import queue
        import threading
        from . import mavlink as mav_io
        from . import mavlink_codec
        from .serial_control import RELEASE_REPEATS_S, SerialControlTunnel
        self._asyncio, self._rx = asyncio, queue.Queue()
        self._release_repeats = RELEASE_REPEATS_S
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="ubx-configure-tunnel", daemon=True)
        self._thread.start()
        dev = {"GPS1": mavlink_codec.m.SERIAL_CONTROL_DEV_GPS1, "GPS2": mavlink_codec.m.SERIAL_CONTROL_DEV_GPS2}[device]

        async def start():
            link = mav_io.MavlinkLink(connection, target_system=target_system, timesync_interval_s=0)
            await link.start()
            t_end = self.loop.time() + heartbeat_timeout_s
            while not link.connected and self.loop.time() < t_end:
                await asyncio.sleep(0.02)
            if not link.connected:
                await link.close()
                raise ReceiverConfigError(f"no HEARTBEAT from autopilot {target_system} on {connection} in "
                                          f"{heartbeat_timeout_s:g} s")
            tunnel = SerialControlTunnel(link, dev, baudrate=baud)
            tunnel.listeners.append(self._rx.put)
            return link, tunnel, asyncio.ensure_future(tunnel.run())

        try:
            self.link, self.tunnel, self._poller = self._call(start())
        except BaseException:
            self._stop_loop()
            raise

    def _call(self, coro):
        return self._asyncio.run_coroutine_threadsafe(coro, self.loop).result()

    def write(self, data: bytes) -> None:
        self.loop.call_soon_threadsafe(self.tunnel.write, bytes(data))

    def read_some(self, timeout_s: float) -> bytes:
        import queue
        try:
            return self._rx.get(timeout=max(timeout_s, 1e-3))
        except queue.Empty:
            return b""

    def close(self) -> None:
        async def stop():
            self._poller.cancel()
            for k, dt in enumerate(self._release_repeats):
                await self._asyncio.sleep(dt - (self._release_repeats[k - 1] if k else 0.0))
                self.tunnel.release()
            await self.link.close()
        try:
            self._call(stop())
        finally:
            self._stop_loop()

    def _stop_loop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout=5.0)
        self.loop.close()


def open_transport(address: str, baud: int = 38400):
    """``tcp://HOST:PORT``, ``udp://HOST:PORT`` or a serial device."""
    if address.startswith(("tcp://", "udp://")):
        host, _, port = address[6:].rpartition(":")
        if not host or not port.isdigit():
            raise ReceiverConfigError(f"address {address!r}: expected {address[:6]}HOST:PORT")
        if address.startswith("udp://"):
            return UdpTransport(host, int(port))
        return SerialTransport(f"socket://{host}:{port}", baud)
    return SerialTransport(address, baud)


class AckScanner:
    """Checksum-checked UBX frames out of a byte stream; keeps the ACK-ACK / ACK-NAK answers
    ``(acked, class, id)`` and counts everything else (NMEA, other UBX, garbage)."""

    def __init__(self):
        from .ubx import ubx_checksum
        self._checksum = ubx_checksum
        self._buf = bytearray()
        self.bytes_in = 0
        self.frames = 0
        self.frames_by_id: Counter = Counter()      # (class, id) -> checked frames

    def feed(self, data: bytes) -> list[tuple[bool, int, int]]:
        self.bytes_in += len(data)
        buf = self._buf
        buf += data
        out = []
        while True:
            j = buf.find(UBX_SYNC)
            if j < 0:
                del buf[:len(buf) - 1 if buf.endswith(UBX_SYNC[:1]) else len(buf)]
                break
            del buf[:j]
            if len(buf) < 6:
                break
            n = buf[4] | (buf[5] << 8)
            if n > 8192:
                del buf[:2]
                continue
            if len(buf) < n + 8:
                break
            body = bytes(buf[2:6 + n])
            if bytes(self._checksum(body)) != bytes(buf[6 + n:8 + n]):
                del buf[:2]
                continue
            del buf[:8 + n]
            self.frames += 1
            self.frames_by_id[(body[0], body[1])] += 1
            if body[0] == ACK_CLASS and body[1] in (ACK_ACK, ACK_NAK) and n == 2:
                out.append((body[1] == ACK_ACK, body[4], body[5]))
        return out


def send_items(transport, items: list[ConfigItem], *, timeout_s: float = 1.5, drain_s: float = 0.3,
               clock=time.monotonic) -> tuple[list[ItemResult], AckScanner]:
    """Send each frame and wait for its ACK/NAK; stop at the first silence (the rest: 'not sent').

    First ``drain_s`` of input is read and its answers dropped: an ACK still buffered in the port
    (the autopilot's GPS driver configures the receiver too, with the same CFG-VALSET) must not
    pass for the answer to our first frame."""
    scanner = AckScanner()
    results: list[ItemResult] = []
    t_end = clock() + drain_s
    while clock() < t_end:
        scanner.feed(transport.read_some(t_end - clock()))
    for k, item in enumerate(items):
        t0 = clock()
        transport.write(item.frame)
        status = "timeout"
        while status == "timeout" and clock() - t0 < timeout_s:
            for acked, cls, mid in scanner.feed(transport.read_some(timeout_s - (clock() - t0))):
                if (cls, mid) == item.cfg_class_id:
                    status = "ack" if acked else "nak"
                    break
        results.append(ItemResult(item, status, round(clock() - t0, 3)))
        if status == "timeout" and k < len(items) - 1:
            results += [ItemResult(it, "not sent") for it in items[k + 1:]]
            break
    return results, scanner


RXM_RAWX_ID, RXM_SFRBX_ID = (0x02, 0x15), (0x02, 0x13)


def watch_output(transport, scanner: AckScanner, seconds: float, clock=time.monotonic) -> Counter:
    """The UBX frames (by class and id) the receiver sends in the next ``seconds``."""
    before = Counter(scanner.frames_by_id)
    t_end = clock() + seconds
    while clock() < t_end:
        scanner.feed(transport.read_some(t_end - clock()))
    return scanner.frames_by_id - before


def verify_report(seen: Counter, seconds: float, rate_hz: float) -> tuple[bool, str]:
    """(raw output flowing, text) from what :func:`watch_output` saw."""
    n_raw, n_sfrbx = seen[RXM_RAWX_ID], seen[RXM_SFRBX_ID]
    text = (f"in {seconds:g} s: RXM-RAWX {n_raw} ({n_raw / seconds:.1f} Hz, configured {rate_hz:g} Hz), "
            f"RXM-SFRBX {n_sfrbx}, other UBX {sum(seen.values()) - n_raw - n_sfrbx}")
    if n_raw == 0:
        return False, text + ": no raw observations although acknowledged (another program re-configured it?)"
    if n_raw / seconds < 0.5 * rate_hz:
        text += ": fewer than configured (frames lost: baud rate too low for the output?)"
    return True, text


def silence_hint(scanner: AckScanner, address: str, baud: int) -> str:
    """Why no answer came, as far as the bytes tell."""
    if scanner.bytes_in == 0:
        return f"nothing at all came back from {address}: no receiver there, or it is powered off"
    if scanner.frames == 0:
        return (f"{scanner.bytes_in} bytes came back but no UBX frame: wrong baud rate ({baud})? "
                "or UBX input disabled on that port")
    return (f"{scanner.frames} UBX frames came back but no answer to this one: UBX input disabled on "
            "that port, or not a u-blox of that generation (--generation)")


# ----------------------------------------------------------------------------------------- CLI
def build_items(args) -> list[ConfigItem]:
    if args.generation == "f9":
        return f9_items(receiver_port=args.receiver_port, rate_hz=args.rate_hz, moving_base=args.moving_base,
                        systems=args.systems, layers=args.layers, receiver_baud=args.receiver_baud)
    if args.receiver_baud:
        raise ReceiverConfigError("--receiver-baud is for --generation f9 (M8: CFG-PRT, use u-center)")
    if args.systems:
        raise ReceiverConfigError("--systems is for --generation f9 (M8: CFG-GNSS, use u-center)")
    if args.receiver_port != "uart1":
        raise ReceiverConfigError("--receiver-port is for --generation f9: an M8's CFG-MSG sets the port "
                                  "the command arrives on")
    return m8_items(rate_hz=args.rate_hz, moving_base=args.moving_base, layers=args.layers)


def run_configure_cli(args) -> int:
    import sys
    try:
        items = build_items(args)
    except ReceiverConfigError as exc:
        print(f"companion gnss configure: error: {exc}", file=sys.stderr)
        return 2
    if not args.mavlink and args.address and not args.address.startswith(("tcp://", "udp://")):
        warn = bandwidth_warning(args.generation, args.rate_hz, args.receiver_baud or args.baud)
        if warn:
            print(f"companion gnss configure: warning: {warn}", file=sys.stderr)
    if args.dry_run:
        for it in items:
            print(f"{it.key} = {it.value}: {it.frame.hex(' ')}")
        return 0
    if bool(args.address) == bool(args.mavlink):
        print("companion gnss configure: error: give the receiver's port (a serial device, tcp://HOST:PORT "
              "or udp://HOST:PORT) or --mavlink CONNECTION (through the autopilot), one of them; or --dry-run",
              file=sys.stderr)
        return 2
    where = args.address or f"{args.device} of the autopilot on {args.mavlink}"
    try:
        if args.mavlink:
            transport = TunnelTransport(args.mavlink, args.device, baud=args.tunnel_baud,
                                        target_system=args.target_system)
        else:
            transport = open_transport(args.address, args.baud)
    except ReceiverConfigError as exc:
        print(f"companion gnss configure: error: {exc}", file=sys.stderr)
        return 2
    seen = None
    try:
        results, scanner = send_items(transport, items, timeout_s=args.timeout_s)
        # after a baud-rate change the receiver no longer talks at the rate the port is open with
        if args.verify_s > 0 and all(r.status == "ack" for r in results) and not args.receiver_baud:
            seen = watch_output(transport, scanner, args.verify_s)
    finally:
        transport.close()
    for r in results:
        answer = {"ack": "ACK", "nak": "NAK (rejected)", "timeout": f"no answer in {args.timeout_s:g} s",
                  "not sent": "not sent"}[r.status]
        print(f"{r.item.key} = {r.item.value}: {answer}")
    naks = [r for r in results if r.status == "nak"]
    silent = [r for r in results if r.status == "timeout"]
    if silent and len(results) > 1 and silent[0] is results[-1] and results[-1].item.key.endswith("_BAUDRATE"):
        # the receiver switched before its ACK reached us: expected, not an error
        print(f"companion gnss configure: the receiver now talks at {args.receiver_baud} baud (no ACK at the "
              f"old rate is normal): use --baud {args.receiver_baud} from now on")
        silent = []
    if silent:
        print(f"companion gnss configure: error: {silent[0].item.key}: no ACK/NAK; "
              + silence_hint(scanner, where, args.baud if not args.mavlink else args.tunnel_baud), file=sys.stderr)
        return 1
    if naks:
        hint = ""
        if "flash" in args.layers and args.generation == "f9":
            hint = " (a receiver without flash rejects the flash layer: try --layers ram,bbr)"
        print(f"companion gnss configure: error: rejected by the receiver: {', '.join(r.item.key for r in naks)}"
              + hint, file=sys.stderr)
        return 1
    print(f"companion gnss configure: {len(results)} settings acknowledged by the receiver at {where}")
    if seen is not None:
        ok, text = verify_report(seen, args.verify_s, args.rate_hz)
        print(f"companion gnss configure: {'' if ok else 'error: '}output {text}",
              file=sys.stdout if ok else sys.stderr)
        return 0 if ok else 1
    return 0


def register(gnss_subparsers) -> None:
    p = gnss_subparsers.add_parser(
        "configure", help="switch a u-blox receiver's raw output on (RXM-RAWX, RXM-SFRBX, rate)",
        description="Send the u-blox configuration the companion needs (RXM-RAWX and RXM-SFRBX on, "
                    "measurement rate; NAV-RELPOSNED for a moving-base rover), one setting per message, "
                    "and report the receiver's ACK/NAK for each.")
    p.add_argument("address", nargs="?",
                   help="serial device (/dev/ttyACM0), tcp://HOST:PORT or udp://HOST:PORT")
    p.add_argument("--baud", type=int, default=38400, help="serial baud rate (u-blox default 38400)")
    p.add_argument("--mavlink", metavar="CONNECTION",
                   help="through the autopilot instead (ArduPilot SERIAL_CONTROL; pymavlink connection string, "
                        "e.g. udpin:127.0.0.1:14550, with the service stopped). The GPS port is locked for the "
                        "run and given back at the end. ArduPilot re-configures its receiver unless "
                        "GPS_AUTO_CONFIG 0; with GPS_RAW_DATA 0 it switches raw messages off again")
    p.add_argument("--device", choices=["GPS1", "GPS2"], default="GPS1", help="--mavlink: the autopilot's GPS port")
    p.add_argument("--tunnel-baud", type=int, default=0, help="--mavlink: set the GPS port's baud rate (0: leave it)")
    p.add_argument("--target-system", type=int, default=1, help="--mavlink: the autopilot's system id")
    p.add_argument("--generation", choices=["f9", "m8"], default="f9",
                   help="f9: CFG-VALSET keys (ZED-F9P, NEO-M9N ...); m8: legacy CFG-MSG/CFG-RATE (NEO-M8T/M8P)")
    p.add_argument("--receiver-port", choices=list(F9_PORTS), default="uart1",
                   help="f9: the receiver port whose output is set (the one wired to the companion or autopilot)")
    p.add_argument("--rate-hz", type=float, default=5.0, help="measurement rate (default 5 Hz)")
    p.add_argument("--moving-base", action="store_true",
                   help="also NAV-RELPOSNED (dual-antenna heading: the moving-base rover receiver)")
    p.add_argument("--systems", help="f9: enable exactly these constellations, e.g. G,E,C,J (R = GLONASS); "
                                     "default: leave the signal configuration alone")
    p.add_argument("--layers", default="ram,bbr,flash",
                   help="where the settings go: ram, bbr, flash, comma-separated (default all three; "
                        "m8: bbr/flash = CFG-CFG save)")
    p.add_argument("--receiver-baud", type=int,
                   help="f9: also set the receiver's UART baud rate (sent last; then use --baud with it). "
                        "Raw output at 5 Hz needs more than the default 38400")
    p.add_argument("--timeout-s", type=float, default=1.5, help="wait this long for each ACK/NAK")
    p.add_argument("--verify-s", type=float, default=0.0,
                   help="afterwards, listen this long and count RXM-RAWX / RXM-SFRBX (exit 1 if no RXM-RAWX)")
    p.add_argument("--dry-run", action="store_true", help="print the frames (hex) instead of sending them")
    p.set_defaults(func=run_configure_cli)


__all__ = ["ConfigItem", "ItemResult", "ReceiverConfigError", "f9_items", "m8_items", "open_transport",
           "send_items", "AckScanner", "register"]
