"""`companion gnss configure` against a fake u-blox on 127.0.0.1 (issue 15, receiver set-up).

The fake receiver parses the bytes it gets with pyubx2's UBXReader (as a receiver would read its
input, independently of how companion built them), records the settings, and answers every CFG
message with ACK-ACK, or ACK-NAK for the settings it is told to reject, or not at all."""
from __future__ import annotations

import socket
import threading

import pytest

pyubx2 = pytest.importorskip("pyubx2")
from pyubx2 import SET, UBXMessage, UBXReader  # noqa: E402

from companion.cli import main  # noqa: E402
from companion.io.ubx_configure import AckScanner, bandwidth_warning, raw_output_bytes_per_s  # noqa: E402

NMEA_NOISE = b"$GNGGA,,,,,,0,00,99.99,,,,,,*56\r\n"


def _valset_keys(msg) -> dict:
    return {k: v for k, v in vars(msg).items() if k.startswith("CFG_")}


class FakeReceiver:
    """Answers what it reads; ``reject(msg)`` True -> ACK-NAK; ``silent`` -> no answer at all."""

    def __init__(self, proto: str = "tcp", reject=lambda msg: False, silent=False, output: list[bytes] = (),
                 output_period_s: float = 0.1):
        """``output``: frames sent in turn every ``output_period_s`` once a client is connected
        (tcp), as a receiver streams its messages besides the answers."""
        self.reject, self.silent, self.proto = reject, silent, proto
        self.output, self.output_period_s = list(output), output_period_s
        self._send_lock = threading.Lock()
        self.received: list = []                     # parsed pyubx2 messages, in order
        kind = socket.SOCK_STREAM if proto == "tcp" else socket.SOCK_DGRAM
        self.sock = socket.socket(socket.AF_INET, kind)
        self.sock.bind(("127.0.0.1", 0))
        self.address = f"{proto}://127.0.0.1:{self.sock.getsockname()[1]}"
        if proto == "tcp":
            self.sock.listen(1)
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _answer(self, msg) -> bytes:
        if self.silent is True or (callable(self.silent) and self.silent(msg)):
            return NMEA_NOISE                        # its NMEA goes on, no answer to the command
        ack = "ACK-NAK" if self.reject(msg) else "ACK-ACK"
        return NMEA_NOISE + UBXMessage("ACK", ack, 0, clsID=msg.msg_cls[0], msgID=msg.msg_id[0]).serialize()

    def _serve(self) -> None:
        if self.proto == "tcp":
            conn, _ = self.sock.accept()
            if self.output:
                threading.Thread(target=self._stream, args=(conn,), daemon=True).start()
            with conn, conn.makefile("rb") as stream:
                for _raw, msg in UBXReader(stream, msgmode=SET):
                    self.received.append(msg)
                    with self._send_lock:
                        conn.sendall(self._answer(msg))
        else:
            while True:
                try:
                    data, peer = self.sock.recvfrom(65536)
                except OSError:
                    return
                msg = UBXReader.parse(data, msgmode=SET)
                self.received.append(msg)
                self.sock.sendto(self._answer(msg), peer)

    def _stream(self, conn) -> None:
        import time
        k = 0
        while True:
            time.sleep(self.output_period_s)
            try:
                with self._send_lock:
                    conn.sendall(self.output[k % len(self.output)])
            except OSError:
                return
            k += 1

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def receiver():
    made = []

    def make(**kw):
        made.append(FakeReceiver(**kw))
        return made[-1]
    yield make
    for r in made:
        r.close()


def test_f9_keys_values_and_layers_as_the_receiver_reads_them(receiver, capsys):
    rx = receiver()
    rc = main(["gnss", "configure", rx.address, "--receiver-port", "uart2", "--rate-hz", "10", "--moving-base",
               "--layers", "ram,bbr"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert all(m.identity == "CFG-VALSET" for m in rx.received)
    assert all(len(_valset_keys(m)) == 1 for m in rx.received)           # one key per message: ACK per key
    assert all((m.ram, m.bbr, m.flash) == (1, 1, 0) for m in rx.received)
    got = {k: v for m in rx.received for k, v in _valset_keys(m).items()}
    assert got == {"CFG_UART2OUTPROT_UBX": 1, "CFG_MSGOUT_UBX_RXM_RAWX_UART2": 1,
                   "CFG_MSGOUT_UBX_RXM_SFRBX_UART2": 1, "CFG_RATE_MEAS": 100, "CFG_RATE_NAV": 1,
                   "CFG_MSGOUT_UBX_NAV_RELPOSNED_UART2": 1}
    assert out.count(": ACK") == 6


def test_nak_is_reported_by_key_and_the_other_keys_still_go(receiver, capsys):
    rx = receiver(reject=lambda m: "CFG_SIGNAL_GLO_ENA" in vars(m))
    rc = main(["gnss", "configure", rx.address, "--systems", "G,E,R"])
    cap = capsys.readouterr()
    assert rc == 1
    assert "CFG_SIGNAL_GLO_ENA = 1: NAK" in cap.out and "rejected by the receiver: CFG_SIGNAL_GLO_ENA" in cap.err
    got = {k: v for m in rx.received for k, v in _valset_keys(m).items()}
    assert {k: got[k] for k in got if k.startswith("CFG_SIGNAL")} == {
        "CFG_SIGNAL_GPS_ENA": 1, "CFG_SIGNAL_GAL_ENA": 1, "CFG_SIGNAL_BDS_ENA": 0, "CFG_SIGNAL_QZSS_ENA": 0,
        "CFG_SIGNAL_GLO_ENA": 1}
    assert cap.out.count(": ACK") == len(rx.received) - 1


def test_silent_receiver_stops_at_the_first_key_with_a_reason(receiver, capsys):
    rx = receiver(silent=True)
    rc = main(["gnss", "configure", rx.address, "--timeout-s", "0.3"])
    cap = capsys.readouterr()
    assert rc == 1
    assert len(rx.received) == 1 and "not sent" in cap.out
    # NMEA but no UBX frame came back -> the baud-rate hint
    assert "no ACK/NAK" in cap.err and "no UBX frame" in cap.err


def test_m8_legacy_messages(receiver, capsys):
    rx = receiver(proto="udp")
    rc = main(["gnss", "configure", rx.address, "--generation", "m8", "--rate-hz", "2", "--layers", "ram,flash"])
    assert rc == 0, capsys.readouterr()
    ids = [m.identity for m in rx.received]
    assert ids == ["CFG-MSG", "CFG-MSG", "CFG-RATE", "CFG-CFG"]
    # 3-byte CFG-MSG: class, id, rate on the port it arrived on
    assert [bytes(m.payload) for m in rx.received[:2]] == [bytes([0x02, 0x15, 1]), bytes([0x02, 0x13, 1])]
    rate, save = rx.received[2], rx.received[3]
    assert (rate.measRate, rate.navRate, rate.timeRef) == (500, 1, 1)
    assert (save.devBBR, save.devFlash) == (0, 1) and save.saveMask != b"\x00\x00\x00\x00"


def test_dry_run_frames_parse_back(capsys):
    assert main(["gnss", "configure", "--dry-run", "--rate-hz", "4"]) == 0
    lines = capsys.readouterr().out.splitlines()
    parsed = {}
    for ln in lines:
        frame = bytes.fromhex(ln.rpartition(": ")[2])
        parsed.update(_valset_keys(UBXReader.parse(frame, msgmode=SET)))
    assert parsed["CFG_RATE_MEAS"] == 250 and parsed["CFG_MSGOUT_UBX_RXM_RAWX_UART1"] == 1


def test_option_errors(capsys):
    assert main(["gnss", "configure", "--dry-run", "--rate-hz", "100"]) == 2
    assert main(["gnss", "configure", "--dry-run", "--generation", "m8", "--systems", "G"]) == 2
    assert main(["gnss", "configure", "--dry-run", "--layers", "eeprom"]) == 2
    assert main(["gnss", "configure"]) == 2                                   # no address, no dry run
    assert main(["gnss", "configure", "tcp://127.0.0.1"]) == 2                # no port number
    assert "error" in capsys.readouterr().err


def test_ack_scanner_skips_noise_and_bad_checksums():
    ack = UBXMessage("ACK", "ACK-ACK", 0, clsID=0x06, msgID=0x8A).serialize()
    nak = UBXMessage("ACK", "ACK-NAK", 0, clsID=0x06, msgID=0x01).serialize()
    broken = ack[:-1] + bytes([ack[-1] ^ 0xFF])
    s = AckScanner()
    stream = b"\xb5" + NMEA_NOISE + broken + ack + nak
    got = [a for i in range(0, len(stream), 3) for a in s.feed(stream[i:i + 3])]     # split anywhere
    assert got == [(True, 0x06, 0x8A), (False, 0x06, 0x01)]


def test_through_the_autopilots_serial_control_tunnel(capsys):
    """--mavlink: the frames reach the receiver on the fake ArduPilot's GPS1 port in SERIAL_CONTROL
    requests, the ACKs come back in its replies, and the port is unlocked at the end."""
    import asyncio

    from tests._fake_ardupilot import FakeArduPilot, free_udp_port

    seen: list = []
    consumed = [0]

    def receiver_on_gps1(t: float) -> bytes:       # the u-blox behind the autopilot's port
        scanner_input = bytes(ap.uart_written[consumed[0]:])
        out = b""
        while len(scanner_input) >= 8:
            n = scanner_input[4] | (scanner_input[5] << 8)
            if len(scanner_input) < n + 8:
                break
            msg = UBXReader.parse(scanner_input[:n + 8], msgmode=SET)
            consumed[0] += n + 8
            scanner_input = scanner_input[n + 8:]
            seen.append(msg)
            out += UBXMessage("ACK", "ACK-ACK", 0, clsID=msg.msg_cls[0], msgID=msg.msg_id[0]).serialize()
        return out

    ap = FakeArduPilot(receiver_on_gps1)

    async def scenario():
        port = free_udp_port()
        loop = asyncio.get_running_loop()
        await loop.create_datagram_endpoint(lambda: ap, remote_addr=("127.0.0.1", port))
        ap.start()
        try:
            return await loop.run_in_executor(None, main, ["gnss", "configure", "--mavlink",
                                                            f"udpin:127.0.0.1:{port}", "--rate-hz", "5"])
        finally:
            ap.stop()

    rc = asyncio.run(scenario())
    out = capsys.readouterr().out
    assert rc == 0, out
    got = {k: v for m in seen for k, v in _valset_keys(m).items()}
    assert got["CFG_MSGOUT_UBX_RXM_RAWX_UART1"] == 1 and got["CFG_RATE_MEAS"] == 200
    assert out.count(": ACK") == len(seen) == 5
    assert ap.lock_changes and ap.lock_changes[-1][1] is False       # the autopilot has its port back


def test_new_baud_rate_goes_last_and_its_lost_ack_is_expected(receiver, capsys):
    rx = receiver(silent=lambda m: "CFG_UART1_BAUDRATE" in vars(m))     # switched before answering
    rc = main(["gnss", "configure", rx.address, "--receiver-baud", "460800", "--timeout-s", "0.3"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert list(_valset_keys(rx.received[-1])) == ["CFG_UART1_BAUDRATE"]
    assert rx.received[-1].CFG_UART1_BAUDRATE == 460800
    assert "--baud 460800" in out


def test_raw_output_that_does_not_fit_the_uart_is_warned_about(capsys):
    # the F9 default (5 Hz) does not fit the receiver's factory 38400 baud; 460800 carries it
    assert raw_output_bytes_per_s("f9", 5.0) > 0.8 * 38400 / 10 and bandwidth_warning("f9", 5.0, 38400)
    assert bandwidth_warning("f9", 5.0, 460800) is None
    assert main(["gnss", "configure", "/dev/ttyNOTHERE", "--dry-run"]) == 0
    assert "warning: at 5 Hz" in capsys.readouterr().err
    assert main(["gnss", "configure", "/dev/ttyNOTHERE", "--dry-run", "--receiver-baud", "460800"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_nothing_at_all_back_says_so(capsys):
    with socket.socket() as srv:               # accepts, reads, never writes: no receiver behind it
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        rc = main(["gnss", "configure", f"tcp://127.0.0.1:{srv.getsockname()[1]}", "--timeout-s", "0.3"])
    assert rc == 1 and "nothing at all came back" in capsys.readouterr().err


def _file_frames(identity: str, n: int) -> list[bytes]:
    from tests._data import data_path
    with open(data_path("qzsl6tool-hiroshima-rtcm3-ubx/20230919-114418.ubx"), "rb") as fh:
        out = [raw for raw, msg in UBXReader(fh, protfilter=pyubx2.UBX_PROTOCOL, quitonerror=pyubx2.ERR_IGNORE)
               if msg is not None and msg.identity == identity]
    return out[:n]


@pytest.mark.real_data
def test_verify_counts_the_raw_output_that_follows(receiver, capsys):
    """--verify-s: after the ACKs, the receiver's RXM-RAWX (here every 0.1 s, with an SFRBX
    between two) are counted; a receiver that keeps silent about raw data fails the run."""
    raw, sfrbx = _file_frames("RXM-RAWX", 2), _file_frames("RXM-SFRBX", 2)
    rx = receiver(output=[raw[0], sfrbx[0], raw[1], sfrbx[1]], output_period_s=0.05)
    rc = main(["gnss", "configure", rx.address, "--rate-hz", "10", "--verify-s", "1.0"])
    out = capsys.readouterr().out
    assert rc == 0, out
    n_raw = int(out.split("RXM-RAWX ")[1].split()[0])
    assert 5 <= n_raw <= 12 and "RXM-SFRBX" in out          # 10 Hz for 1 s, give or take the thread's timing
    rx2 = receiver(output=[UBXMessage("NAV", "NAV-PVT", pyubx2.GET, iTOW=1, fixType=3).serialize()])
    assert main(["gnss", "configure", rx2.address, "--verify-s", "0.5"]) == 1
    assert "no raw observations although acknowledged" in capsys.readouterr().err
