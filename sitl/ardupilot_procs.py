"""Processes of ``python -m sitl ardupilot``: the ArduCopter SITL binary, ``companion run`` and,
with ``--gnss raw``, the raw GNSS receiver (:mod:`sitl.ardupilot_gnss`).

All are started in their own session, so a Ctrl-C in the terminal reaches only the harness,
which then stops them in order (SIGTERM, then SIGKILL after a grace period).  SITL also exits by
itself when its parent dies.
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from .instance_lock import release, reserve_instance

REPO = Path(__file__).resolve().parent.parent
DEFAULT_BIN = REPO.parent / "shared" / "ardupilot" / "arducopter"
BIN_ENV = "COMPANION_ARDUPILOT_BIN"
HOME = "-35.363261,149.165230,584,353"     # the launcher's default (Canberra)


def find_binary(path: str | None = None) -> Path:
    """--sitl-bin, else $COMPANION_ARDUPILOT_BIN, else <repo>/../shared/ardupilot/arducopter."""
    return Path(path or os.environ.get(BIN_ENV) or DEFAULT_BIN).resolve()


def binary_problem(binary: Path) -> str | None:
    """Why ``binary`` cannot run here (missing, not executable, wrong CPU/ABI), or None."""
    if not binary.is_file():
        return f"ArduCopter SITL binary not found: {binary} (set --sitl-bin or ${BIN_ENV})"
    if not os.access(binary, os.X_OK):
        return f"ArduCopter SITL binary is not executable: {binary}"
    try:
        r = subprocess.run([str(binary), "--help"], capture_output=True, timeout=10)
    except OSError as exc:          # ENOEXEC: another architecture
        return f"ArduCopter SITL binary cannot run on this machine: {exc}"
    except subprocess.TimeoutExpired:
        return f"ArduCopter SITL binary did not answer --help within 10 s: {binary}"
    if r.returncode < 0:            # SIGILL: built for a newer CPU
        return f"ArduCopter SITL binary died with signal {-r.returncode} on this CPU: {binary}"
    if b"--defaults" not in r.stdout + r.stderr:
        return f"{binary} does not look like an ArduPilot SITL binary (no --defaults in --help)"
    return None


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("0.0.0.0", port))       # SITL binds all interfaces
            return True
        except OSError:
            return False


def free_instance(max_instance: int = 20) -> tuple[int, object]:
    """(the first SITL instance whose four TCP ports (5760+10*I .. +3) are free, its reservation:
    hold it until SITL stops; sitl.instance_lock)."""
    return reserve_instance("arducopter", max_instance,
                            lambda i: all(_port_free(5760 + 10 * i + k) for k in range(4)))


def stop_process(proc: subprocess.Popen | None, name: str, grace_s: float = 10.0) -> int | None:
    """SIGTERM ``proc`` (only that pid), SIGKILL it after ``grace_s``; its exit code."""
    if proc is None:
        return None
    if proc.poll() is None:
        try:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            print(f"  {name} did not stop in {grace_s:.0f} s: killing pid {proc.pid}", flush=True)
            proc.kill()
            proc.wait(timeout=5)
        except ProcessLookupError:
            pass
    return proc.returncode


class ArduCopterSitl:
    """One ArduCopter SITL instance with ``parm`` files loaded after the binary's defaults.

    Parameters are wiped at start (``-w``) so the files are authoritative, as with the launcher.
    Serial ports: SERIAL0 ``tcp:127.0.0.1:5760+10*I`` (SITL waits for a connection there before it
    starts), SERIAL1 ``+2``, SERIAL2 ``+3``.
    """

    def __init__(self, binary: Path, parm_files: list[Path], run_dir: Path, instance: int | None = None,
                 start_time_unix_s: int | None = None):
        """``start_time_unix_s``: SITL's ``--start-time`` (its clock, and so its GPS time, is this
        plus its boot time); None = SITL's own default (the host's clock at start)."""
        self.start_time_unix_s = start_time_unix_s
        self.binary = Path(binary)
        self.parm_files = [Path(p).resolve() for p in parm_files]
        self.run_dir = Path(run_dir)
        self._reservation = None
        if instance is None:
            instance, self._reservation = free_instance()
        self.instance = instance
        self.proc: subprocess.Popen | None = None
        self._log = None

    def port(self, serial: int) -> int:
        return 5760 + 10 * self.instance + (0 if serial == 0 else serial + 1)

    @property
    def log_path(self) -> Path:
        return self.run_dir / "arducopter.log"

    def start(self, timeout_s: float = 20.0) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        defaults = [self.binary.parent / "copter-sitl-defaults.parm"]
        defaults = [p for p in defaults if p.is_file()] + self.parm_files
        args = [str(self.binary), "--model", "+", "--speedup", "1", "--home", HOME, f"-I{self.instance}",
                "--defaults", ",".join(str(p) for p in defaults), "--sim-address", "127.0.0.1",
                "--serial0", "tcp:0", "-w"]
        if self.start_time_unix_s is not None:
            args += ["--start-time", str(int(self.start_time_unix_s))]
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(args, cwd=str(self.run_dir), stdout=self._log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True)
        want = f"SERIAL0 on TCP port {self.port(0)}".encode()
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"SITL exited early (code {self.proc.returncode}): "
                                   f"{self.log_path.read_text(errors='replace')[-1500:]}")
            if want in self.log_path.read_bytes():
                return
            time.sleep(0.1)
        raise RuntimeError(f"SITL did not open SERIAL0 within {timeout_s:.0f} s (log {self.log_path})")

    def stop(self) -> int | None:
        code = stop_process(self.proc, "SITL", grace_s=5.0)
        if self._log is not None:
            self._log.close()
            self._log = None
        release(self._reservation)
        self._reservation = None
        return code


# ------------------------------------------------------------------------------------------------
# companion run

def companion_config(deploy_toml: str, *, connection: str, log_dir: str, gnss_source: str,
                     output_mode: str, overrides: dict[str, str] | None = None) -> str:
    """``deploy/companion.toml`` with only the connection, log directory, GNSS source and output
    mode replaced (line by line, so every other key and comment stays as shipped).

    ``overrides``: {"section.key": TOML value} for experiments (``--set``), e.g.
    {"filter.zupt_enabled": "true"}; a key the file does not show is added to its section."""
    section = ""
    out = []
    repl = {("mavlink", "connection"): f'"{connection}"', ("log", "dir"): f'"{log_dir}"',
            ("gnss", "source"): f'"{gnss_source}"', ("output", "mode"): f'"{output_mode}"'}
    for k, v in (overrides or {}).items():
        sec, _, key = k.rpartition(".")
        repl[(sec, key)] = v
    done = set()
    for line in deploy_toml.splitlines():
        m = re.match(r"\s*\[([^\]]+)\]", line)
        if m:
            section = m.group(1).strip()
        m = re.match(r"(\s*)([A-Za-z_]+)(\s*=\s*)", line)
        if m and (section, m.group(2)) in repl:
            key = (section, m.group(2))
            line = f'{m.group(1)}{m.group(2)}{m.group(3)}{repl[key]}'
            done.add(key)
        out.append(line)
    header = re.compile(r"\s*\[([^\]]+)\]")
    line_of = {header.match(l).group(1).strip(): n for n, l in enumerate(out) if header.match(l)}
    extra = {tuple(k.rpartition(".")[::2]) for k in overrides or {}}
    # keys the file does not show (experiments only): inserted under their section header, the
    # last section first so the line numbers of the others stay valid
    for sec, key in sorted(set(repl) - done, key=lambda k: -line_of.get(k[0], -1)):
        if sec not in line_of or (sec, key) not in extra:
            raise ValueError(f"deploy/companion.toml lacks [{sec}] {key}")
        out.insert(line_of[sec] + 1, f"{key} = {repl[(sec, key)]}")
    return "\n".join(out) + "\n"


class _Child:
    """A harness child process in its own session with its output in ``log_path``."""

    name = "child"

    def __init__(self, log_path: Path):
        self.log_path = Path(log_path)
        self.proc: subprocess.Popen | None = None
        self._log = None

    def _popen(self, args: list[str], **kw) -> None:
        self._log = open(self.log_path, "wb")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     env=env, cwd=str(REPO), start_new_session=True, **kw)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def cpu_s(self) -> float | None:
        """User + system CPU seconds so far (from /proc)."""
        if not self.alive():
            return None
        try:
            with open(f"/proc/{self.proc.pid}/stat") as fh:
                parts = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            return None
        return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")

    def tail(self, n_bytes: int = 2000) -> str:
        try:
            return self.log_path.read_bytes()[-n_bytes:].decode(errors="replace")
        except OSError:
            return ""

    def stop(self) -> int | None:
        code = stop_process(self.proc, self.name, grace_s=10.0)
        if self._log is not None:
            self._log.close()
            self._log = None
        return code


class CompanionProcess(_Child):
    """``python -m companion.run_cli -v run --config PATH`` with its output in ``log_path``."""

    name = "companion"
    ORIGIN_RE = re.compile(rb"EKF origin (-?\d+\.\d+) (-?\d+\.\d+) (-?\d+\.\d+) m")

    def __init__(self, config_path: Path, log_path: Path):
        super().__init__(log_path)
        self.config_path = Path(config_path)

    def start(self) -> None:
        self._popen([sys.executable, "-m", "companion.run_cli", "-v", "run", "--config", str(self.config_path)])

    def origin(self) -> tuple[float, float, float] | None:
        """The EKF origin the companion's outputs use (lat deg, lon deg, alt m), from its log: the
        last one announced (it adopts the autopilot's when that differs, companion.io.origin)."""
        try:
            found = self.ORIGIN_RE.findall(self.log_path.read_bytes())
        except OSError:
            return None
        return tuple(float(x) for x in found[-1]) if found else None


class GnssReceiverProcess(_Child):
    """``python -m sitl.ardupilot_gnss`` (:mod:`sitl.ardupilot_gnss`): the raw GNSS receiver on a
    pseudo-terminal, the base station and its NTRIP caster, following SITL's truth on
    ``sitl_port``.  The harness makes the pseudo-terminal (raw mode, so the line discipline leaves
    the UBX bytes alone), hands the master side to the process and keeps the slave side open
    until the end; the companion opens the slave by name (:attr:`slave_path`)."""

    name = "GNSS receiver"

    def __init__(self, out_dir: Path, *, sitl_port: int, start_time_unix_s: int, duration_s: float,
                 home: str = HOME, rate_hz: float = 1.0, seed: int = 0):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        super().__init__(self.out_dir / "receiver.log")
        self.args = ["--sitl-port", str(sitl_port), "--start-unix", str(int(start_time_unix_s)), f"--home={home}",
                     "--duration", f"{duration_s:g}", "--rate", f"{rate_hz:g}", "--seed", str(seed),
                     "--out", str(self.out_dir)]
        self.slave_path: str | None = None
        self.ready: dict | None = None
        self._slave: int | None = None

    def start(self, timeout_s: float = 60.0) -> dict:
        import tty
        for stale in ("ready.json", "receiver.json"):
            (self.out_dir / stale).unlink(missing_ok=True)
        master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.slave_path = os.ttyname(self._slave)
        try:
            self._popen([sys.executable, "-m", "sitl.ardupilot_gnss", "--pty-fd", str(master), *self.args],
                        pass_fds=(master,))
        finally:
            os.close(master)
        ready = self.out_dir / "ready.json"
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if ready.exists():
                self.ready = json.loads(ready.read_text())
                return self.ready
            if not self.alive():
                break
            time.sleep(0.1)
        raise RuntimeError(f"GNSS receiver not ready within {timeout_s:.0f} s:\n{self.tail()}")

    def result(self) -> dict | None:
        """Its counters (``receiver.json``, written when it stops)."""
        try:
            return json.loads((self.out_dir / "receiver.json").read_text())
        except (OSError, ValueError):
            return None

    def stop(self) -> int | None:
        code = super().stop()
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None
        return code
