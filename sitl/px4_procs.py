"""Processes of ``python -m sitl px4``: PX4 SITL with SIH physics, and EKF2's status flags from it.

PX4 is started with the shared folder's launcher (``start_sih.sh``: a fresh run directory, no
ULog, ``deploy/px4-vision.params`` turned into ``param set`` lines sourced at boot), in its own
session; ``companion run`` is :class:`sitl.ardupilot_procs.CompanionProcess`, shared with the
ArduPilot harness.  EKF2's control-status flags (``cs_ev_pos`` ...) are not on MAVLink: they are
read with PX4's own ``listener`` client over the instance's socket.
"""
from __future__ import annotations

import os
import re
import socket
import shutil
import subprocess
import time
from pathlib import Path

from .ardupilot_procs import REPO, stop_process
from .instance_lock import release, reserve_instance

DEFAULT_DIST = REPO.parent / "shared" / "px4"
DIST_ENV = "COMPANION_PX4_DIR"
# PX4's UDP ports for instance N (start_sih.sh / px4-rc.mavlink)
ONBOARD_REMOTE_PORT = 14540        # PX4 sends the onboard (companion) link here ...
ONBOARD_LOCAL_PORT = 14580         # ... from here
GCS_LOCAL_PORT = 18570             # the GCS link; PX4 answers whoever last sent to it
DISPLAY_REMOTE_PORT = 19410        # SIH display link: HIL_STATE_QUATERNION (truth)


def find_dist(path: str | None = None) -> Path:
    """--px4-dir, else $COMPANION_PX4_DIR, else <repo>/../shared/px4."""
    return Path(path or os.environ.get(DIST_ENV) or DEFAULT_DIST).resolve()


def dist_problem(dist: Path) -> str | None:
    """Why the PX4 SITL in ``dist`` cannot run here (missing, wrong CPU/ABI), or None."""
    launcher, binary = dist / "start_sih.sh", dist / "bin" / "px4"
    if not launcher.is_file() or not binary.is_file():
        return f"PX4 SITL not found in {dist} (needs start_sih.sh and bin/px4; set --px4-dir or ${DIST_ENV})"
    if not os.access(binary, os.X_OK):
        return f"PX4 SITL binary is not executable: {binary}"
    try:
        r = subprocess.run([str(binary), "-h"], capture_output=True, timeout=10)
    except OSError as exc:          # ENOEXEC: another architecture
        return f"PX4 SITL binary cannot run on this machine: {exc}"
    except subprocess.TimeoutExpired:
        return f"PX4 SITL binary did not answer -h within 10 s: {binary}"
    if r.returncode < 0:            # SIGILL / missing glibc symbols kill it before main
        return f"PX4 SITL binary died with signal {-r.returncode} on this CPU: {binary}"
    if b"px4" not in (r.stdout + r.stderr).lower():
        return f"{binary} does not look like PX4 (-h: {(r.stdout + r.stderr)[:200]!r})"
    return None


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def _lock_held(path: Path) -> bool:
    """A running PX4 holds an flock on its /tmp/px4_lock-N; one that died leaves the file behind
    (a PX4 that exits at start-up does), which must not take the instance away for good."""
    import fcntl
    try:
        with open(path, "rb") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                return True
            fcntl.flock(fh, fcntl.LOCK_UN)
            return False
    except FileNotFoundError:
        return False


def instance_free(i: int) -> bool:
    """Whether PX4 instance ``i``'s lock file is not held and its UDP ports are free."""
    ports = (ONBOARD_REMOTE_PORT + i, ONBOARD_LOCAL_PORT + i, GCS_LOCAL_PORT + i, DISPLAY_REMOTE_PORT + i)
    return not _lock_held(Path(f"/tmp/px4_lock-{i}")) and all(_udp_free(p) for p in ports)


def free_instance(max_instance: int = 10, first: int = 0) -> tuple[int, object]:
    """(the first free PX4 instance from ``first`` on, its reservation: hold it until PX4 stops;
    sitl.instance_lock)."""
    return reserve_instance("px4", max_instance, instance_free, first)


def read_params(path: Path) -> dict[str, float]:
    """``NAME VALUE`` lines (``#`` comments) of a deploy/ parameter file."""
    out = {}
    for line in Path(path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, value = re.split(r"[\s,=]+", line, maxsplit=1)
            out[name] = float(value)
    return out


def hardware_only(name: str) -> bool:
    """Serial-port parameters (MAV_n_CONFIG, SER_*): they exist only on boards with those ports;
    SITL's MAVLink links are started by its start-up script on UDP instead."""
    return bool(re.fullmatch(r"MAV_\d_CONFIG|SER_\w+", name))


class Px4Sitl:
    """One PX4 SIH instance (quad X) with ``params`` set at boot; writes only below ``run_dir``
    (and PX4's own /tmp/px4_lock-N, /tmp/px4-sock-N)."""

    def __init__(self, dist: Path, params: dict[str, float], run_dir: Path, instance: int | None = None,
                 ulog_topics: dict[str, int] | None = None, first_instance: int = 0):
        self.dist = Path(dist)
        self.params = dict(params)
        # topic -> interval ms (0 = every sample): a ULog of just these, from boot to shutdown
        # (PX4's logger reads WORKDIR/etc/logging/logger_topics.txt instead of its profile);
        # None = no ULog (a full one is about 15 MB a minute)
        self.ulog_topics = dict(ulog_topics) if ulog_topics else None
        self.run_dir = Path(run_dir)
        self._reservation = None
        if instance is None:
            instance, self._reservation = free_instance(first=first_instance)
        self.instance = instance
        self.proc: subprocess.Popen | None = None
        self._log = None

    @property
    def work_dir(self) -> Path:
        return self.run_dir / f"inst{self.instance}"

    @property
    def log_path(self) -> Path:
        return self.run_dir / "px4.log"

    @property
    def system_id(self) -> int:
        """MAV_SYS_ID: start_sih.sh gives instance N system id N + 1 (so a link to instance 1
        must target system 2, not the default 1)."""
        return self.instance + 1

    def port(self, name: str) -> int:
        return {"onboard_remote": ONBOARD_REMOTE_PORT, "gcs_local": GCS_LOCAL_PORT,
                "display_remote": DISPLAY_REMOTE_PORT}[name] + self.instance

    def start(self, timeout_s: float = 30.0) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        param_file = self.run_dir / "params.sh"
        params = dict(self.params)
        if self.ulog_topics:
            params["SDLOG_MODE"] = 2                 # log from boot until shutdown, armed or not
        param_file.write_text("".join(f"param set {k} {v:g}\n" for k, v in params.items()))
        self._log = open(self.log_path, "wb")
        env = dict(os.environ, PX4_RUN_DIR=str(self.run_dir))
        if self.ulog_topics:
            # the logger reads ./etc/logging/logger_topics.txt, and ./etc is the (read-only) ROMFS:
            # run on a copy of it (720 kB) with the list added; start_sih.sh -f would delete it,
            # so WORKDIR is cleared here
            shutil.rmtree(self.work_dir, ignore_errors=True)
            shutil.copytree(self.dist / "etc", self.work_dir / "etc", symlinks=True)
            topics = self.work_dir / "etc" / "logging" / "logger_topics.txt"
            topics.parent.mkdir(parents=True, exist_ok=True)
            topics.write_text("".join(f"{t} {ms}\n" for t, ms in self.ulog_topics.items()))
            flags = []
        else:
            flags = ["-f", "-n"]
        self.proc = subprocess.Popen(["/bin/sh", str(self.dist / "start_sih.sh"), *flags, "-i", str(self.instance),
                                      "-p", str(param_file)], cwd=str(self.run_dir), env=env, stdout=self._log,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"PX4 exited early (code {self.proc.returncode}): {self.log_text()[-1500:]}")
            if "Startup script returned successfully" in self.log_text():
                return
            time.sleep(0.2)
        raise RuntimeError(f"PX4 did not finish its start-up script within {timeout_s:.0f} s (log {self.log_path})")

    def ulog_files(self) -> list[Path]:
        """The ULog files PX4 wrote (WORKDIR/log/<date>/<time>.ulg), oldest first."""
        return sorted((self.work_dir / "log").rglob("*.ulg"))

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def estimator_flags(self, timeout_s: float = 5.0) -> dict[str, bool] | None:
        """EKF2's estimator_status_flags (cs_* control status, fs_*/reject_* faults) now, or None."""
        if not self.alive():
            return None
        try:
            r = subprocess.run([str(self.work_dir / "bin" / "px4-listener"), "--instance", str(self.instance),
                                "estimator_status_flags", "-n", "1"], capture_output=True, timeout=timeout_s,
                               cwd=str(self.work_dir))
        except (OSError, subprocess.TimeoutExpired):
            return None
        return parse_listener_flags(r.stdout.decode(errors="replace"))

    def stop(self) -> int | None:
        code = stop_process(self.proc, "PX4", grace_s=10.0)
        if self._log is not None:
            self._log.close()
            self._log = None
        release(self._reservation)
        self._reservation = None
        return code


def parse_listener_flags(text: str) -> dict[str, bool] | None:
    """``    cs_ev_pos: True`` lines of ``listener estimator_status_flags`` -> {name: bool}."""
    flags = {m.group(1): m.group(2) == "True" for m in re.finditer(r"^\s*(\w+): (True|False)\s*$", text, re.MULTILINE)}
    return flags or None
