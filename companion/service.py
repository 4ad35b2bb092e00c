"""The companion service: asyncio wiring around the deterministic :class:`~companion.pipeline.NavPipeline`.

``Service(config).run()`` runs until SIGINT/SIGTERM (or :meth:`Service.stop`):

* **Supervised tasks** (:meth:`Service._supervise`): ``mavlink`` (link to the autopilot, the
  SERIAL_CONTROL tunnel for a receiver on the autopilot's GPS port -- detect, then claim:
  :class:`~companion.io.serial_control.PortClaim` takes the port only while RXM-RAWX flows and
  gives it back on shutdown --, the IMU/attitude/time inputs and the estimate outputs), ``gnss-serial`` (a receiver on a local serial port), ``corrections``
  (NTRIP / serial radio / MQTT / file), ``output`` (EKF origin repeats), ``health`` and
  ``telemetry`` (MQTT).  A task that raises is logged with its traceback, counted and restarted
  after an exponential backoff (0.5 s doubling to 30 s, reset after a minute of good running).
* **Determinism**: every input is written to the field log (kinds ``mavlink`` = one frame as
  received, ``ubx``, ``rtcm``; ``event`` for the configuration, start, origin, stop and periodic
  health) *and then* handed to the pipeline, synchronously, in the same order.  The pipeline
  produces solutions by decimating the IMU stream, so ``companion replay`` of the log reproduces
  every ``solution`` record bit for bit.  Frames that fail the MAVLink CRC are counted by the link
  and never reach the log or the pipeline (they carry nothing usable).
* **Outputs**: each solution is logged (kind ``solution``, :func:`~companion.log_records.encode_solution`;
  the per aid source status at ``log.aid_status_rate_hz`` as kind ``aid_status``,
  :mod:`companion.aid_status_record`, also on MQTT ``<prefix>/aid_status``)
  and, when the pipeline marks it injectable (status nav/coasting within the configured sigmas),
  sent at once -- no timer, no queue: VISION_POSITION_ESTIMATE (default, ``reset_counter`` =
  number of filter (re)initialisations, time stamp = boot time of the IMU sample the estimate is
  valid for), ODOMETRY or GPS_INPUT.  The EKF origin of VISION/ODOMETRY is read back
  (:mod:`companion.io.origin`): ours is proposed at the first injectable position, rounded to
  what SET_GPS_GLOBAL_ORIGIN carries (1e-7 deg, cm), sent (``output.set_ekf_origin``; repeated
  until GPS_GLOBAL_ORIGIN confirms it) and the outputs use the origin the autopilot reports --
  ours confirmed, or its own adopted when it already had one (too far: no vision/odometry).
  State changes of the filter (initialised, re-initialised, injecting / not injecting, tight /
  loose), of the GPS port claim and of the origin are announced with STATUSTEXT.
* **Health**: every ``HEALTH_INTERVAL_S`` a one-line summary is logged (inputs and rates, filter
  status and sigmas, outputs, rejections) and the full report (:meth:`health`) is written to the
  field log and MQTT; SIGUSR1 logs the full report at once.
* **Untrusted input, bounded** (issue 14): correction bytes are handled in slices of at most
  ``corrections.max_bytes_per_turn`` (default 512) with a yield to the event loop between
  slices, so a burst can never hold the IMU path for more than one slice's decoding; correction
  chunks from the network or a radio and UBX chunks from a local port beyond a byte-rate cap
  (``corrections.max_rate_bps``, ``gnss.max_rate_bps``; a recorded file is not capped) are
  dropped before they are logged or decoded (counted, one warning per 10 s; replay sees exactly
  what the pipeline saw).  The field log has a total size cap with retention
  (``log.max_total_bytes``), is fsync-ed at least every ``FSYNC_MAX_INTERVAL_S`` and pauses on a
  full disk: the writer's events become STATUSTEXT, navigation goes on.
* **Secrets**: the configuration copy in the field log is redacted (``***`` for secret fields;
  replay does not need them), and the service warns when its configuration file can be read by
  other users.
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import math
import os
import signal
import time
from collections import Counter

from .pipeline import NavPipeline
from .log_records import config_event, encode_solution

log = logging.getLogger(__name__)

MAV_SEVERITY_ERROR, MAV_SEVERITY_INFO = 3, 6         # MAVLink common.xml MAV_SEVERITY

HEALTH_INTERVAL_S = 5.0
BACKOFF_INITIAL_S = 0.5
BACKOFF_MAX_S = 30.0
BACKOFF_RESET_AFTER_S = 60.0
from .io.origin import ORIGIN_REPEAT_S  # noqa: E402,F401  (SET_GPS_GLOBAL_ORIGIN repeats)
# a power cut or kill -9 loses at most this much field log plus one write + fsync (the flusher
# writes when the oldest queued record is this old), whatever the config says: <= 0.5 s with a
# 0.1-s margin for a slow card
FSYNC_MAX_INTERVAL_S = 0.4
DEFAULT_MAX_TOTAL_LOG_BYTES = 1 << 30
DEFAULT_CORRECTIONS_MAX_RATE_BPS = 64_000.0
DEFAULT_UBX_MAX_RATE_BPS = 256_000.0
DEFAULT_MAX_BYTES_PER_TURN = 512
DROP_LOG_INTERVAL_S = 10.0


def _json_default(x):
    try:
        return x.item()          # numpy scalars
    except Exception:
        return str(x)


#: the field log's config record (companion.log_records.config_event: secrets redacted)
redacted_config_event = config_event


class Service:
    def __init__(self, config, *, install_signal_handlers: bool = True):
        self.cfg = config
        self.install_signal_handlers = install_signal_handlers
        self.pipeline = NavPipeline(config)
        self.fieldlog = None
        self.link = None
        self.tunnel = None
        self.telemetry = None
        self.port_claim = None                  # PortClaim when gnss.source = mavlink_serial_control
        self.origin = None                      # the Origin the vision/odometry outputs use
        self.origin_mgr = None
        if config.output.mode != "gps_input":
            from .io.origin import OriginManager
            self.origin_mgr = OriginManager(send_set=config.output.set_ekf_origin,
                                            target_system=config.mavlink.target_system,
                                            target_component=config.mavlink.target_component)
        self._origin_reboots_seen = 0
        self.counters: Counter = Counter()
        self.restarts: Counter = Counter()
        self.task_errors: dict[str, str] = {}
        self.record_counts: Counter = Counter()
        self.record_bytes: Counter = Counter()
        self._rate_prev = (time.monotonic(), Counter())
        self._stop = None
        self._tasks: list[asyncio.Task] = []
        self._t_start = time.monotonic()
        self._last_telemetry = 0.0
        self.nmea = None                        # NmeaSink when [nmea] is enabled
        self._nmea_slot = None
        self._named_value_slot = None
        from .aid_status_record import AidStatusPacer
        self._aid_status = AidStatusPacer(getattr(config.log, "aid_status_rate_hz", 0.0))
        self._last_rtcm_mono_ns = None
        self._fragmenter = None
        from .sdnotify import SystemdNotifier
        self.notifier = SystemdNotifier()       # Type=notify + WatchdogSec under systemd, else no-op
        self._caps: dict = {}                 # input kind -> ByteRateCap
        self._last_drop_log: dict[str, float] = {}
        from .status_page import StatusBoard
        self.status_board = StatusBoard()       # what the status page shows (fed even without the page)
        self.status_server = None
        self._restore_kernels = None            # undoes filter.compiled_kernels at shutdown
        self.params = None                      # ParameterServer: the GCS reads/sets CC_* parameters
        if config.mavlink.parameters:
            from .io.mavlink_params import ParameterServer
            self.params = ParameterServer(config, system_id=config.mavlink.source_system,
                                          component_id=config.mavlink.source_component,
                                          persist=config.mavlink.parameters_persist, on_change=self._apply_config)

    # ------------------------------------------------------------------ lifecycle
    def stop(self) -> None:
        if self._stop is not None:
            self._stop.set()

    async def run(self) -> None:
        from .io.mavlink_signing import signing_preflight
        key_warning = signing_preflight(self.cfg)      # SigningKeyError: no start without the key
        if os.environ.get("COMPANION_CPU_PROFILE"):    # measurements only (companion.cpu_profile)
            from .cpu_profile import install
            install(os.environ["COMPANION_CPU_PROFILE"])
        loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if self.install_signal_handlers:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, self._on_signal, sig)
            loop.add_signal_handler(signal.SIGUSR1, self._log_full_health)
        from . import config as config_module
        exposed = getattr(config_module, "secrets_readable_by_others", lambda cfg: None)(self.cfg)
        if exposed:
            # in the health report too: a warning at start-up scrolls away
            self.counters["config file readable by others"] += 1
            log.warning("%s", exposed)
        if key_warning:
            self.counters["signing key file readable by others"] += 1
            log.warning("%s", key_warning)
        lc = self.cfg.log
        cfg_event = redacted_config_event(self.cfg)
        if lc.enabled:
            from .io.fieldlog import FieldLogWriter
            self.fieldlog = FieldLogWriter(
                lc.dir, max_bytes=lc.max_bytes, fsync_interval_s=min(lc.fsync_interval_s, FSYNC_MAX_INTERVAL_S),
                max_total_bytes=getattr(lc, "max_total_bytes", DEFAULT_MAX_TOTAL_LOG_BYTES),
                preamble=[("event", cfg_event)])     # every file replays, even after retention
            log.info("field log %s", self.fieldlog.current_path)
        self._event({"event": "start", "config": self.cfg.source_path})
        self._record("event", time.monotonic_ns(), cfg_event)
        specs = [("mavlink", self._mavlink_task), ("output", self._output_task), ("health", self._health_task)]
        if self.cfg.gnss.source == "serial":
            specs.append(("gnss-serial", self._gnss_serial_task))
        if self.cfg.corrections.source != "none":
            specs.append(("corrections", self._corrections_task))
        if self.cfg.telemetry.enabled:
            specs.append(("telemetry", self._telemetry_task))
        from .nav.imu_kernel import use_reference_paths, warm_up
        kc = self.cfg.filter.compiled_kernels
        if kc == "off" or (kc == "auto" and not self.cfg.filter.rtk_enabled):
            self._restore_kernels = use_reference_paths()
        t_warm = warm_up()              # compiled kernels now (cache: ~0.5 s), not at the first IMU sample
        if t_warm > 5.0:
            log.warning("compiling the IMU kernels took %.1f s (no cache yet: NUMBA_CACHE_DIR, "
                        "python -m companion.nav.imu_kernel at install)", t_warm)
        await self._start_status_page()
        self._tasks = [asyncio.create_task(self._supervise(n, f), name=n) for n, f in specs]
        log.info("companion running: %s", ", ".join(n for n, _ in specs))
        self.notifier.ready("running: " + ", ".join(n for n, _ in specs))
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()

    async def _start_status_page(self) -> None:
        sp = self.cfg.status_page
        if not sp.enabled:
            return
        from .status_page import StatusPageServer
        server = StatusPageServer(self.status_board, sp.address, sp.port)
        try:
            await server.start()
        except OSError as exc:             # port in use, address not on this host: navigate anyway
            self.counters["status page not started"] += 1
            log.warning("status page not started on %s:%d: %s", sp.address, sp.port, exc.strerror or exc)
            self.status_board.add_event(4, f"status page not started on {sp.address}:{sp.port}")
            return
        self.status_server = server
        log.info("status page: http://%s:%d/", sp.address, server.port)

    def _apply_config(self, cfg, keys) -> None:
        """A parameter the ground station set (companion.io.mavlink_params): thresholds, rates and
        the installation follow at once (the field log records the change, so a replay applies it
        at the same record); the output mode is saved but takes effect at the next start (the
        autopilot's source parameters must change with it)."""
        live = cfg
        if cfg.output.mode != self.cfg.output.mode:
            live = dataclasses.replace(cfg, output=dataclasses.replace(cfg.output, mode=self.cfg.output.mode))
            self._announce_events([(MAV_SEVERITY_INFO, f"output {cfg.output.mode} after restart")])
        self.cfg = live
        self.pipeline.apply_settings(live)
        self._record("event", time.monotonic_ns(), redacted_config_event(live, event="config_change"))
        if self.fieldlog is not None:
            self.fieldlog.set_preamble([("event", redacted_config_event(live))])   # files after this one
        log.warning("ground station set %s", ", ".join(keys))

    def _on_signal(self, sig) -> None:
        log.info("%s received: shutting down", signal.Signals(sig).name)
        self.stop()

    async def _shutdown(self) -> None:
        self.notifier.stopping()
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        h = self.health()
        if self.link is not None:
            await self.link.close()
            self.link = None
        self._event({"event": "stop", "health": h})
        if self.status_server is not None:
            await self.status_server.close()
            self.status_server = None
        if self._restore_kernels is not None:
            self._restore_kernels()
            self._restore_kernels = None
        if self.nmea is not None:
            self.nmea.close()
        if self.fieldlog is not None:
            self.fieldlog.close()
            log.info("field log closed: %d records in %s", self.fieldlog.records_written,
                     ", ".join(str(p) for p in self.fieldlog.files))
        log.info("companion stopped")

    async def _supervise(self, name: str, factory) -> None:
        backoff = BACKOFF_INITIAL_S
        while True:
            t0 = time.monotonic()
            try:
                await factory()
                log.info("task %s finished", name)
                return
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                self.restarts[name] += 1
                self.task_errors[name] = repr(exc)
                if time.monotonic() - t0 > BACKOFF_RESET_AFTER_S:
                    backoff = BACKOFF_INITIAL_S
                log.exception("task %s failed (restart %d in %.1f s)", name, self.restarts[name], backoff)
                await asyncio.sleep(backoff)
                backoff = min(BACKOFF_MAX_S, backoff * 2.0)

    # ------------------------------------------------------------------ field log
    def _record(self, kind: str, t_ns: int, data: bytes) -> None:
        self.record_counts[kind] += 1
        self.record_bytes[kind] += len(data)
        if self.fieldlog is not None:
            try:
                if not self.fieldlog.write(kind, data, t_ns):
                    self.counters["field log records dropped"] += 1
            except Exception:
                # the writer handles I/O errors itself; this is a bug: never per record in the log
                self.counters["field log write errors"] += 1
                if self.counters["field log write errors"] <= 3:
                    log.exception("field log write failed")

    def _admit(self, kind: str, data: bytes) -> bool:
        """Byte-rate cap of an untrusted input kind: False = drop this chunk (count, warn at most
        every DROP_LOG_INTERVAL_S).  Dropped before logging, so replay sees what the pipeline saw."""
        cap = self._caps.get(kind)
        if cap is None:
            from .io.ratecap import ByteRateCap
            if kind == "rtcm":
                bps = getattr(self.cfg.corrections, "max_rate_bps", DEFAULT_CORRECTIONS_MAX_RATE_BPS)
            else:
                bps = getattr(self.cfg.gnss, "max_rate_bps", DEFAULT_UBX_MAX_RATE_BPS)
            cap = self._caps[kind] = ByteRateCap(bps)
        if cap.admit(len(data)):
            return True
        key = f"{kind} dropped: rate cap"
        self.counters[key] += 1
        self.counters[f"{kind} bytes dropped: rate cap"] += len(data)
        now = time.monotonic()
        if now - self._last_drop_log.get(kind, -math.inf) >= DROP_LOG_INTERVAL_S:
            self._last_drop_log[kind] = now
            log.warning("%s input faster than %.0f B/s: chunks dropped (%d so far)", kind, cap.rate_bps,
                        self.counters[key])
        return False

    def _event(self, obj: dict) -> None:
        self._record("event", time.monotonic_ns(), json.dumps(obj, default=_json_default).encode())
        if obj.get("event") == "status":
            self.status_board.add_event(obj.get("severity", 6), obj.get("text", ""))

    # ------------------------------------------------------------------ MAVLink
    async def _mavlink_task(self) -> None:
        from .io.mavlink import link_from_config
        link = link_from_config(self.cfg.mavlink)
        self._subscribe(link)
        await link.start()
        self.link = link
        children = []
        claim = None
        try:
            g = self.cfg.gnss
            if g.source == "mavlink_serial_control":
                claim = self._port_claim(link)
                # the replies reach the pipeline through the logged MAVLink stream: the tunnel
                # keeps no copy (queue_replies=False), the claim reads them as a listener
                children.append(asyncio.create_task(claim.run(), name="serial-control-claim"))
            pipe = self.pipeline
            pet = self.notifier.pet
            pacer = self._pace_reads(link)
            seen = [None]              # the last IMU sample the pacer saw

            def on_message(lm) -> None:
                pet()                  # the IMU path is alive (the watchdog restarts a stuck one)
                self._record("mavlink", lm.t_mono_ns, lm.raw)
                sols = pipe.feed_mavlink_record(lm.t_mono_ns, lm.msg)
                if sols:
                    self._outputs(sols)
                if pipe.events:
                    self._announce()
                if pacer is not None and pipe.last_imu is not seen[0]:
                    seen[0] = pipe.last_imu
                    if seen[0] is not None:
                        pacer.observe(lm.t_mono_ns * 1e-9, seen[0].t_gps)
            # synchronously from the link's receive callback: record, feed and send in the same
            # event-loop pass as the datagram, no queue hop (an exception ends this task as before)
            await link.deliver_to(on_message)
        finally:
            for c in children:
                c.cancel()
            await asyncio.gather(*children, return_exceptions=True)
            if claim is not None:
                claim.close()          # ArduPilot's lock has no timeout: never leave it held
                self._announce_events(claim.drain_events())
            self._last_link_health = link.health()
            if self.link is link:
                self.link = None
            await link.close()

    def _pace_reads(self, link):
        """The link's reader sleeps between reads until shortly before the next output slot's IMU
        sample (companion.io.rx_pacing), unless ``mavlink.rx_pacing`` is off."""
        mc = self.cfg.mavlink
        if not mc.rx_pacing:
            return None
        from .io.rx_pacing import OutputPacedReads
        pacer = OutputPacedReads(margin_s=mc.rx_pacing_margin_s)
        pipe = self.pipeline
        link.rx_pause = lambda: pacer.pause_s(time.monotonic(), pipe.next_output_t_gps())
        return pacer

    def _subscribe(self, link) -> None:
        """What the service takes from the link besides the logged stream: GPS_GLOBAL_ORIGIN and
        the parameter protocol."""
        if self.origin_mgr is not None:
            link.subscribe("GPS_GLOBAL_ORIGIN",
                           lambda msg, t_ns: self.origin_mgr.on_gps_global_origin(msg, time.monotonic()))
        if self.params is not None:
            for kind in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"):
                link.subscribe(kind, self._on_param_message)

    def _on_param_message(self, msg, t_ns) -> None:
        for reply in self.params.handle(msg):
            if self.link is not None:
                self.link.send(reply)
                self.counters["sent " + reply.get_type()] += 1

    def _port_claim(self, link):
        """The SERIAL_CONTROL tunnel to the receiver on the autopilot's GPS port and the state
        machine that decides when to hold that port (companion.io.serial_control)."""
        from .io.serial_control import PortClaim, SerialControlTunnel
        from pymavlink.dialects.v20 import ardupilotmega as mav
        g = self.cfg.gnss
        dev = mav.SERIAL_CONTROL_DEV_GPS1 if g.serial_control_device == "GPS1" else mav.SERIAL_CONTROL_DEV_GPS2
        self.tunnel = SerialControlTunnel(link, dev, poll_interval_s=g.serial_control_poll_interval_s,
                                          baudrate=g.serial_control_baud, queue_replies=False)
        self.port_claim = PortClaim(self.tunnel, mode=g.serial_control_claim, probe_s=g.serial_control_probe_s,
                                    release_after_s=g.serial_control_release_after_s,
                                    retry_max_s=g.serial_control_retry_max_s,
                                    probe_when_armed=g.serial_control_probe_armed,
                                    enable_sfrbx=g.serial_control_enable_sfrbx)
        return self.port_claim

    # ------------------------------------------------------------------ outputs
    def _outputs(self, sols) -> None:
        for sol in sols:
            self._record("solution", time.monotonic_ns(), encode_solution(sol))
            self.counters["solutions"] += 1
            self.status_board.add_solution(sol)
            if sol.extras.get("inject"):
                self._send_estimate(sol)
            else:
                self.counters["estimates withheld"] += 1
        self._aid_status_records(sols)
        tc = self.cfg.telemetry
        if self.telemetry is not None and sols:
            now = time.monotonic()
            if now - self._last_telemetry >= 1.0 / tc.rate_hz:
                self._last_telemetry = now
                self.telemetry.publish_solution(sols[-1])
        if self.cfg.nmea.enabled and sols:
            self._send_nmea(sols[-1])
        if self.cfg.output.named_value_rate_hz > 0 and sols:
            self._send_named_values(sols[-1])

    def _aid_status_records(self, sols) -> None:
        """Per aid source status (companion.aid_status_record) at log.aid_status_rate_hz of GPS
        time: a field log record of its own, and MQTT <prefix>/aid_status."""
        for obj, payload in self._aid_status.records(self.pipeline, sols):
            self._record("aid_status", time.monotonic_ns(), payload)
            self.status_board.set_aid_status(obj)
            if self.telemetry is not None:
                self.telemetry.publish_aid_status(obj)

    def _send_named_values(self, sol) -> None:
        """The companion's state for the ground station (companion.io.gcs_values), paced by GPS time."""
        slot = math.floor(sol.t_gps * self.cfg.output.named_value_rate_hz)
        if slot == self._named_value_slot or self.link is None or not self.link.connected:
            return
        self._named_value_slot = slot
        from .io.gcs_values import named_values
        for msg in named_values(sol, int((time.monotonic() - self._t_start) * 1000)):
            self.link.send(msg)
        self.counters["named values sent"] += 1

    def _send_nmea(self, sol) -> None:
        """NMEA at nmea.rate_hz slots of GPS time (as the MAVLink outputs: paced by the data)."""
        nc = self.cfg.nmea
        slot = math.floor(sol.t_gps * nc.rate_hz)
        if slot == self._nmea_slot:
            return
        self._nmea_slot = slot
        from .io.nmea import NmeaSink, nmea_sentences
        if self.nmea is None:
            try:
                self.nmea = NmeaSink(nc.destination)
            except (OSError, ValueError) as exc:
                self.counters["nmea output unavailable"] += 1
                if self.counters["nmea output unavailable"] == 1:
                    log.error("NMEA output %s cannot be opened: %s", nc.destination, exc)
                return
        recent = self._last_rtcm_mono_ns is not None and time.monotonic_ns() - self._last_rtcm_mono_ns < 30e9
        self.nmea.send(nmea_sentences(sol, leap_seconds=self.cfg.gnss.leap_seconds,
                                      geoid_undulation_m=self.cfg.output.geoid_undulation_m, talker=nc.talker,
                                      sentences=nc.sentences, differential=recent))

    def _send_estimate(self, sol) -> None:
        from .io import mavlink_encode as mv
        link = self.link
        if link is None or not link.connected:
            self.counters["estimates not sent: link down"] += 1
            return
        o = self.cfg.output
        t_boot_us = int(sol.extras.get("t_boot_us") or 0)
        if o.mode == "gps_input":
            msg = mv.gps_input(sol, t_boot_us=t_boot_us, gps_id=o.gps_input_id,
                               geoid_undulation_m=o.geoid_undulation_m)
        else:
            origin = self._output_origin(sol)
            if origin is None:
                return
            # an origin that moved after estimates went out is a reset for the autopilot
            reset = sol.reset_counter + self.origin_mgr.epoch
            if o.mode == "odometry":
                sr = sol.sigma_r_n_m
                msg = mv.odometry(sol, origin, reset, t_boot_us,
                                  quality=mv.quality_from_sigma(math.hypot(sr[0], sr[1]), o.max_sigma_h_m),
                                  geoid_undulation_m=o.geoid_undulation_m)
            else:
                msg = mv.vision_position_estimate(sol, origin, reset, t_boot_us,
                                                  geoid_undulation_m=o.geoid_undulation_m)
        if link.send(msg):
            self.counters[f"sent {msg.get_type()}"] += 1
            if o.mode != "gps_input":
                self.origin_mgr.mark_sent()
                if not self.origin_mgr.confirmed:
                    self.counters["estimates sent: origin unconfirmed"] += 1
        else:
            self.counters["estimates not sent: send error"] += 1

    def _output_origin(self, sol):
        """The origin to send this estimate about (companion.io.origin), or None = not now."""
        from .io.mavlink_encode import Origin
        mgr = self.origin_mgr
        now = time.monotonic()
        if mgr.ours is None:
            o = Origin.from_ecef(sol.r_e, self.cfg.output.geoid_undulation_m)
            mgr.propose(o, now)
            p = mgr.ours
            self._event({"event": "origin proposed", **p.as_dict()})
            log.info("origin proposed: %.7f %.7f %.2f m (our first injectable position)", p.lat_e7 * 1e-7,
                     p.lon_e7 * 1e-7, p.alt_mm * 1e-3)
            self._maybe_send_origin()
        origin = mgr.output_origin(now)
        self._announce_events(mgr.drain_events())
        if origin is None:
            self.counters["estimates not sent: autopilot origin too far" if mgr.refused
                          else "estimates held: origin not read back"] += 1
            return None
        if origin != self.origin:
            self.origin = origin
            u = mgr.used
            self._event({"event": "origin", **u.as_dict(), "confirmed": mgr.confirmed, "mismatch_m": mgr.mismatch_m,
                         "epoch": mgr.epoch})
            log.info("EKF origin %.7f %.7f %.3f m (%s; ours %s m off)", math.degrees(origin.lat_rad),
                     math.degrees(origin.lon_rad), origin.alt_m,
                     "read back from the autopilot" if mgr.confirmed else "ours, not confirmed", mgr.mismatch_m)
        return origin

    def _maybe_send_origin(self) -> None:
        """SET_GPS_GLOBAL_ORIGIN repeats and GPS_GLOBAL_ORIGIN requests (companion.io.origin)."""
        mgr = self.origin_mgr
        if mgr is None or self.link is None:
            return
        reboots = self.pipeline.counters.get("autopilot reboots", 0)
        if reboots != self._origin_reboots_seen:
            self._origin_reboots_seen = reboots
            mgr.on_autopilot_reboot(time.monotonic())
        for msg in mgr.tick(time.monotonic(), self.link.connected):
            if self.link.send(msg):
                name = msg.get_type() if msg.get_type() != "COMMAND_LONG" else "REQUEST_MESSAGE GPS_GLOBAL_ORIGIN"
                self.counters[f"sent {name}"] += 1
        self._announce_events(mgr.drain_events())

    def _announce_events(self, events) -> None:
        """(MAV_SEVERITY, text) events of the port claim and the origin: field log and STATUSTEXT."""
        from .io.mavlink_encode import statustext
        for sev, text in events:
            self._event({"event": "status", "severity": sev, "text": text})
            if self.link is not None:
                self.link.send(statustext(sev, "CC: " + text))
                self.counters["sent STATUSTEXT"] += 1

    def _announce(self) -> None:
        from .io.mavlink_encode import statustext
        for sev, text in self.pipeline.drain_events():
            self._event({"event": "status", "severity": sev, "text": text})
            if self.link is not None:
                self.link.send(statustext(sev, "CC: " + text))
                self.counters["sent STATUSTEXT"] += 1

    def _announce_fieldlog(self) -> None:
        """The field log's pause/resume (disk full, space back) as STATUSTEXT: the pilot must know
        the flight is not being recorded."""
        if self.fieldlog is None or not self.fieldlog.events:
            return
        from .io.mavlink_encode import statustext
        for level, text in self.fieldlog.drain_events():
            sev = MAV_SEVERITY_ERROR if level == "error" else MAV_SEVERITY_INFO
            self.counters[f"field log {'paused' if level == 'error' else 'resumed'}"] += 1
            self._event({"event": "status", "severity": sev, "text": text})
            if self.link is not None:
                self.link.send(statustext(sev, "CC: " + text))
                self.counters["sent STATUSTEXT"] += 1

    async def _output_task(self) -> None:
        while True:
            self._maybe_send_origin()
            if self.port_claim is not None and self.port_claim.events:
                self._announce_events(self.port_claim.drain_events())
            if self.pipeline.events:
                self._announce()
            self._announce_fieldlog()
            self.notifier.pet()        # the event loop turns even without an autopilot
            await asyncio.sleep(0.25)

    # ------------------------------------------------------------------ GNSS receiver on a local port
    async def _gnss_serial_task(self) -> None:
        from .io.corrections import SerialCorrectionSource
        sc = self.cfg.gnss.serial
        src = SerialCorrectionSource(sc.port, sc.baud)
        pipe = self.pipeline
        async for raw in src.stream():
            if not self._admit("ubx", raw):
                continue
            t = time.monotonic_ns()
            self._record("ubx", t, raw)
            pipe.feed("ubx", t, raw)

    # ------------------------------------------------------------------ corrections
    async def _corrections_task(self) -> None:
        from .io.corrections import correction_source_from_config
        from .io.rtcm import GpsRtcmDataFragmenter, RtcmFramer
        c = self.cfg.corrections
        src = correction_source_from_config(c, position_cb=self._position_llh)
        self.corrections_source = src
        framer = RtcmFramer() if c.forward_to_autopilot else None
        if framer is not None and self._fragmenter is None:
            self._fragmenter = GpsRtcmDataFragmenter()
        step = max(64, int(getattr(c, "max_bytes_per_turn", DEFAULT_MAX_BYTES_PER_TURN)))
        capped = c.source != "file"          # a local recording is paced by its own rate_bps
        try:
            async for raw in src.stream():
                if capped and not self._admit("rtcm", raw):
                    continue
                for i in range(0, len(raw), step):
                    self._correction_slice(raw[i:i + step], framer)
                    # one slice per event-loop turn: the IMU and the estimates go first
                    await asyncio.sleep(0)
        finally:
            close = getattr(src, "close", None)
            if close is not None:
                close()

    def _correction_slice(self, raw: bytes, framer) -> None:
        t = time.monotonic_ns()
        self._last_rtcm_mono_ns = t
        self._record("rtcm", t, raw)
        self.pipeline.feed("rtcm", t, raw)
        if framer is not None and self.link is not None:
            from .io.mavlink_encode import gps_rtcm_data_messages
            for frame in framer.feed(raw):
                for msg in gps_rtcm_data_messages(frame, self._fragmenter):
                    self.link.send(msg)
                    self.counters["sent GPS_RTCM_DATA"] += 1

    def _position_llh(self):
        sol = self.pipeline.last_solution
        if sol is None or not math.isfinite(float(sol.r_e[0])):
            return None
        from .nav.earth import ecef_to_geodetic
        lat, lon, h = ecef_to_geodetic(sol.r_e)
        return math.degrees(lat), math.degrees(lon), h - self.cfg.output.geoid_undulation_m

    # ------------------------------------------------------------------ telemetry
    async def _telemetry_task(self) -> None:
        from .io.mqtt import MqttTelemetryPublisher
        tc = self.cfg.telemetry
        self.telemetry = MqttTelemetryPublisher(tc.host, tc.port, tc.topic_prefix, rate_hz=tc.rate_hz)
        await self.telemetry.run()

    # ------------------------------------------------------------------ health
    def health(self) -> dict:
        now = time.monotonic()
        t_prev, c_prev = self._rate_prev
        dt = max(now - t_prev, 1e-6)
        rates = {k: round((self.record_counts[k] - c_prev.get(k, 0)) / dt, 1) for k in self.record_counts}
        ph = self.pipeline.health()
        out = {"uptime_s": round(now - self._t_start, 1),
               "inputs": {"records": dict(self.record_counts), "bytes": dict(self.record_bytes),
                          "rates_per_s": rates},
               "filter": ph["filter"],
               "outputs": {k: v for k, v in self.counters.items()},
               "task_restarts": dict(self.restarts), "task_errors": dict(self.task_errors),
               "pipeline": ph["pipeline"], "engine": ph["engine"], "imu_decoder": ph["imu"],
               "time_map": ph["time_map"], "ubx": ph["ubx"], "rtcm": ph["rtcm"]}
        if "aid_sources" in ph:
            out["aid_sources"] = ph["aid_sources"]
        if "rtcm_base" in ph:
            out["rtcm_base"] = ph["rtcm_base"]
        if "imu_cluster" in ph:
            out["imu_cluster"] = ph["imu_cluster"]
        if self.link is not None:
            out["link"] = self.link.health()
        elif getattr(self, "_last_link_health", None) is not None:
            out["link"] = self._last_link_health
        if self.tunnel is not None:
            out["serial_control"] = dict(self.tunnel.counters)
            if self.port_claim is not None:
                out["serial_control"].update(self.port_claim.health())
        if self.origin_mgr is not None:
            out["origin"] = self.origin_mgr.health()
        src = getattr(self, "corrections_source", None)
        if src is not None and hasattr(src, "health"):
            out["corrections_source"] = src.health()
        if self.fieldlog is not None:
            out["field_log"] = {"paused": self.fieldlog.paused, "last_error": self.fieldlog.last_error,
                                **self.fieldlog.counters}
        if self._caps:
            out["rate_caps"] = {k: dict(c.counters) for k, c in self._caps.items()}
        if self.nmea is not None:
            out["nmea"] = {"destination": self.nmea.destination, **self.nmea.counters}
        return out

    def health_line(self, h: dict | None = None) -> str:
        h = h or self.health()
        f = h["filter"]
        r = h["inputs"]["rates_per_s"]
        sig = f.get("sigma_r_ned_m")
        rej = sum(v for k, v in h["engine"].items() if "rejected" in k or "dropped" in k)
        link = h.get("link", {})
        return (f"health: mavlink {r.get('mavlink', 0):.0f}/s rtcm {r.get('rtcm', 0):.1f}/s ubx {r.get('ubx', 0):.1f}/s; "
                f"rover epochs {h['pipeline'].get('rover epochs', 0)} base {h['engine'].get('base epochs', 0)}; "
                f"filter {f.get('status', 'init')} mode {f.get('mode')} init#{f.get('reset_counter')} "
                + ("" if not f.get("satellites_by_system") else "sats " + " ".join(
                    f"{c}{n}" for c, n in f["satellites_by_system"].items()) + " ")
                + f"sigma NED {sig} HPL {f.get('protection_level', {}).get('hpl_m')}; out {sum(v for k, v in h['outputs'].items() if k.startswith('sent ') and 'STATUS' not in k)} "
                f"withheld {h['outputs'].get('estimates withheld', 0)}; rejected {rej}; "
                f"link {'up' if link.get('connected') else 'down'} bad {link.get('bad_data', 0)} "
                f"reboots {h['pipeline'].get('autopilot reboots', 0)} restarts {sum(h['task_restarts'].values())}"
                + ("" if "origin" not in h else "; origin " + (
                    "refused" if h["origin"]["refused"] else "confirmed" if h["origin"]["confirmed"]
                    else "unconfirmed" if h["origin"]["ours"] else "none")
                    + ("" if not h["origin"]["mismatch_m"] else f" (ours {h['origin']['mismatch_m']} m off)"))
                + ("" if "state" not in h.get("serial_control", {}) else f"; GPS port {h['serial_control']['state']}")
                + ("" if "imu_cluster" not in h else "; IMUs healthy " + ",".join(
                    name for name, u in h["imu_cluster"]["units"].items() if u["healthy"]))
                + ("" if "rtk" not in f else f"; RTK {f['rtk']['fix_state']} ({f['rtk']['n_fixed']} fixed of "
                   f"{f['rtk']['n_ambiguities']}, ratio {f['rtk']['fix_ratio']})"))

    def _log_full_health(self) -> None:
        log.warning("health report (SIGUSR1): %s", json.dumps(self.health(), default=str, indent=1))

    async def _health_task(self) -> None:
        while True:
            await asyncio.sleep(HEALTH_INTERVAL_S)
            h = self.health()
            self._rate_prev = (time.monotonic(), Counter(self.record_counts))
            log.info("%s", self.health_line(h))
            self._event({"event": "health", "health": h})
            self.status_board.set_health(h)
            if self.telemetry is not None:
                self.telemetry.publish_health(h)


async def run_service(config) -> None:
    await Service(config).run()


__all__ = ["Service", "run_service", "HEALTH_INTERVAL_S"]
