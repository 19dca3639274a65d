"""The long-running service: source -> pipeline -> Zenoh and MCAP, with reconnects and clean stops.

One thread does all the work (the MCAP writer is not thread-safe and the pipeline is stateful);
Zenoh callbacks only enqueue commands, drained here between blocks. SIGINT/SIGTERM set the stop
event; everything is flushed and closed in `finally`.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from drivers.block import SampleBlock
from drivers.errors import ConfigError, DataError, DriverError, FluxcalError
from drivers.source import Source, open_source
from service.io.calfile import load_calibration, save_calibration

from .config import RATE_MISSING, FluxcalConfig
from .pipeline import Pipeline, PipelineEvent

log = logging.getLogger("fluxcal")


def build_pipeline(cfg: FluxcalConfig, initial=None) -> Pipeline:
    est = cfg.estimator
    positions = np.asarray(cfg.positions_m, float)
    has_geometry = cfg.unit.n_probes > 1 and np.ptp(positions, axis=0).any()
    rate = cfg.rate_hz
    if rate is None:
        raise ConfigError(f"{cfg.path}: {RATE_MISSING}")
    return Pipeline(n_probes=cfg.unit.n_probes, probe_names=cfg.probe_names,
                    positions_m=positions if has_geometry else None, forgetting=est.forgetting,
                    total_nT=est.total_nT, align=est.align, min_samples=est.min_samples,
                    gate_coverage=est.gate_coverage, gate_condition=est.gate_condition,
                    gate_rms_nT=est.gate_rms_nT, check_every_samples=max(1, int(round(est.check_every_s * rate))),
                    window_samples=int(est.window_s * rate), chunk_samples=max(1, int(round(est.update_every_s * rate))),
                    initial=initial)


def open_configured_source(cfg: FluxcalConfig) -> Source:
    kind = getattr(cfg.source, "kind", "sim")
    if kind == "sim":
        import dataclasses

        sim = dataclasses.replace(cfg.sim, duration_s=cfg.source.run_s)
        return open_source("sim", sim, unit=cfg.unit, transport=cfg.source.transport)
    if kind == "replay":
        return open_source("replay", path=cfg.source.path)
    return open_source(kind, cfg.source)


def _say(msg: str) -> None:
    """A line on stderr with the UTC time: a field log is read afterwards, next to the recording."""
    print(f"fluxcal {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}: {msg}", file=sys.stderr, flush=True)


class Daemon:
    """`fluxcal run`: wires a source, the pipeline, the Zenoh bus and the MCAP logger."""

    def __init__(self, cfg: FluxcalConfig, *, stop: threading.Event | None = None,
                 say: Callable[[str], None] | None = None) -> None:
        self.cfg = cfg
        self.stop = stop or threading.Event()
        self.say = say or _say
        self.cal_path = Path(cfg.calibration.file)
        self._pending_error: DriverError | None = None
        self.processing_errors = 0            # blocks whose processing raised (their raw data are kept)
        self._recording_errors_said = 0       # logger errors already said; at most one message a minute
        self._recording_said_at = -1e9
        self._last_processing_say = -1e9
        self._rate_seen: tuple[int, float] = (0, 0.0)       # samples (by seq) and unit-clock seconds seen
        # the unit clock is compared with the configured rate once (CAN has no unit clock: t_s = seq / rate)
        self.rate_checked = getattr(cfg.source, "kind", "") == "can"

    def _initial_calibration(self):
        c = self.cfg.calibration
        if c.initial:
            cal = load_calibration(c.initial)
            self.say(f"starting from calibration {c.initial}")
            return cal
        if self.cal_path.exists():
            try:
                cal = load_calibration(self.cal_path)
                self.say(f"reloaded the persisted calibration {self.cal_path}")
                return cal
            except DataError as e:
                self.say(f"ignoring the persisted calibration: {e}; learning online")
        self.say("no calibration yet: learning online; corrected output starts once it passes the quality gate")
        return None

    def run(self) -> int:
        from service.io.bus import ServiceBus

        cfg = self.cfg
        pipeline = build_pipeline(cfg, self._initial_calibration())
        source = open_configured_source(cfg)
        logger = None
        bus = None
        try:
            bus = ServiceBus(cfg.zenoh, unit=cfg.unit.name, probe_names=cfg.probe_names,
                             state_fn=lambda: self._state(pipeline, source, logger))
            if cfg.mcap.enabled:
                from service.io.recordings.writer import McapLogger

                logger = McapLogger(cfg.mcap.dir, unit=cfg.unit.name, rotate_mb=cfg.mcap.rotate_mb,
                                    rotate_s=cfg.mcap.rotate_s, chunk_size=cfg.mcap.chunk_kb * 1024,
                                    flush_interval_s=cfg.mcap.flush_s,
                                    metadata={"unit": cfg.unit.name, "n_probes": str(cfg.unit.n_probes),
                                              "lsb_nT": repr(cfg.unit.lsb_nT),
                                              "probe_names": json.dumps(cfg.probe_names),
                                              "positions_m": json.dumps(cfg.positions_m),
                                              "config": json.dumps(cfg.raw)})
                from service.io.calfile import calibration_to_dict

                # replay starts from the same calibration, so it reproduces this run bit for bit
                logger.write_event({"kind": "initial", "seq": 0, "calibration":
                                    None if pipeline.calibration is None else calibration_to_dict(pipeline.calibration)})
                st = logger.status()
                if st["current"] is None:
                    # nothing could be opened: say so now, not after a day of data that went nowhere
                    raise ConfigError(f"mcap.dir: {str(cfg.mcap.dir)!r}: cannot record there: {st['last_error']} "
                                      f"(allowed: a directory this user can create and write into; or set "
                                      f"[mcap] enabled = false to run without recording)")
                self.say(f"recording to {cfg.mcap.dir}/")
            self.say(f"publishing on zenoh under fluxcal/{cfg.unit.name}/ "
                     f"(listen {', '.join(getattr(cfg.zenoh, 'listen', []) or ['-'])}"
                     f"{', TLS' if cfg.zenoh.tls.enabled else ''}"
                     f"{', access control' if cfg.zenoh.access.enabled else ''})")
            for ep in cfg.zenoh.exposed():
                self.say(f"warning: {ep} is reachable from other hosts in clear text and without access control: "
                         f"anyone on that network can read the streams and send commands (docs/security.md)")
            self._loop(source, pipeline, bus, logger)
            failed = False
        except BaseException:
            failed = True
            raise
        finally:
            for closer in (source.close, getattr(logger, "close", None), getattr(bus, "close", None)):
                if closer is not None:
                    try:
                        closer()
                    except Exception as e:  # closing must never hide the first error
                        self.say(f"while closing: {e}")
            self.say("stopped (the reason follows)" if failed else "stopped")
        return 0

    def _read_batch(self, source: Source):
        """One block of about `unit.block_ms` of input: fewer, larger blocks cost less CPU per sample.
        A port that fails mid-batch: the samples already read are processed first, the error comes next."""
        if self._pending_error is not None:
            e, self._pending_error = self._pending_error, None
            raise e
        ready = source.wait_readable(0.05)
        if ready is not None:
            if not ready:
                return None
            # input is there: let the rest of the block arrive in the port's buffer, then one read and one
            # parse (when stopping, still read what is there: nothing that arrived is lost)
            self.stop.wait(self.cfg.unit.block_ms / 1000.0)
            return source.read(timeout=0.001)
        first = source.read(timeout=0.05)
        if first is None:
            return None
        parts = [first]
        # let the rest of the block arrive in the port's buffer, then take it in one read and one parse
        if self.stop.wait(self.cfg.unit.block_ms / 1000.0):
            return first
        try:
            more = source.read(timeout=0.001)
            if more is not None:
                parts.append(more)
        except DriverError as e:
            self._pending_error = e
        return parts[0] if len(parts) == 1 else SampleBlock.concat(parts)

    #: unit-clock time over which the configured sample rate is checked, s; and the mismatch said
    RATE_CHECK_S, RATE_TOLERANCE = 5.0, 0.02

    def _check_rate(self, block: SampleBlock) -> None:
        """Once, after RATE_CHECK_S of unit clock: the sample rate the frames show (samples counted by seq
        over the unit clock's t_s) against the configured one, which sets how many samples the estimator's
        durations span. A mismatch is said with the value to set; the service goes on (it is a setting).
        Only spans inside a block count: a gap between blocks (an outage, a restarted unit, a counter
        that wrapped while the cable was out) can make seq and clock disagree, the unit's rate cannot."""
        if block.n_samples < 2:
            return
        dseq = int(block.seq[-1]) - int(block.seq[0])
        dt = float(block.t_s[-1]) - float(block.t_s[0])
        if not (math.isfinite(dt) and dt > 0 and dseq > 0):
            return
        n, span = self._rate_seen
        n, span = n + dseq, span + dt
        self._rate_seen = (n, span)
        if span < self.RATE_CHECK_S:
            return
        self.rate_checked = True
        seen, configured = n / span, self.cfg.rate_hz
        if configured and abs(seen / configured - 1.0) > self.RATE_TOLERANCE:
            key = "source.rate_hz" if getattr(self.cfg.source, "rate_hz", None) else "sim.rate_hz"
            self.say(f"the unit's clock shows {seen:.6g} samples/s but {key} = {configured:g}: the estimator's "
                     f"window_s, check_every_s and update_every_s last {configured / seen:.3g} x the seconds "
                     f"configured; set {key} = {seen:.6g}")

    def _say_recording_trouble(self, logger) -> None:
        """New recording errors (a full disk, a removed drive) are said, at most once a minute, with what
        they cost so far; the logger itself keeps the data it can and retries (docs/recording.md)."""
        st = logger.status()
        now = time.monotonic()
        if st["errors"] > self._recording_errors_said and now - self._recording_said_at >= 60.0:
            self._recording_errors_said, self._recording_said_at = st["errors"], now
            self.say(f"recording trouble: {st['last_error']}; {st['dropped']} message(s) dropped, {st['pending']} "
                     f"waiting to be written; retrying (health: recording)")

    def _process(self, pipeline: Pipeline, block: SampleBlock):
        """pipeline.process, but an error in it (a bug meeting data nobody foresaw) costs that block's
        corrected output, never the service: it is counted, said (at most every 10 s, with the first
        sample's seq) and the next block is processed. Replay meets the same error at the same block."""
        try:
            return pipeline.process(block)
        except Exception as e:          # noqa: BLE001 - a long-running service must outlive one bad block
            self.processing_errors += 1
            now = time.monotonic()
            if now - self._last_processing_say >= 10.0:
                self._last_processing_say = now
                seq0 = int(block.seq[0]) if block.n_samples else -1
                self.say(f"processing failed for the block from seq {seq0} ({block.n_samples} samples): "
                         f"{type(e).__name__}: {e}; its raw samples are recorded, its corrected output is "
                         f"lost; {self.processing_errors} such block(s) so far (health: processing_errors)")
            return None

    def _state(self, pipeline: Pipeline, source: Source, logger) -> dict[str, Any]:
        st = pipeline.state()
        st["health"] = {**source.counters.as_dict(), "processing_errors": self.processing_errors}
        if logger is not None:
            st["recording"] = logger.status()
        return st

    def _loop(self, source: Source, pipeline: Pipeline, bus, logger) -> None:
        backoff = 0.1
        down_since: float | None = None       # monotonic time the input was lost, while it stays down
        attempts = 0
        last_health = 0.0
        announced = pipeline.calibration is not None
        while not self.stop.is_set():
            for cmd in bus.pending_commands():
                self._apply_command(cmd, pipeline, bus, logger)
            block = None                      # nothing to process while the input is down; health still goes out
            if down_since is None:
                try:
                    block = self._read_batch(source)
                except DriverError as e:
                    self.say(f"input lost: {e}; reconnecting (backoff from {backoff:.1f} s)")
                    source.counters.read_errors += 1
                    down_since, attempts = time.monotonic(), 0
            if down_since is not None:
                if self.stop.wait(backoff):
                    break
                backoff = min(backoff * 2, 5.0)
                attempts += 1
                try:
                    source.reopen()
                except DriverError as e:
                    if attempts in (5, 20) or attempts % 100 == 0:
                        self.say(f"input still down after {time.monotonic() - down_since:.0f} s and {attempts} "
                                 f"attempts: {e}; retrying every {backoff:.0f} s")
                else:
                    source.counters.reconnects += 1
                    self.say(f"input reconnected after {time.monotonic() - down_since:.1f} s")
                    down_since, backoff = None, 0.1
            if block is None:
                if source.exhausted:
                    self.say("source exhausted")
                    break
            else:
                if not self.rate_checked:
                    self._check_rate(block)
                # the raw block is kept and published first: whatever happens to its processing, it is not lost
                if logger is not None:
                    logger.write_raw(block)
                bus.publish_raw(block)
                out = self._process(pipeline, block)     # None: failed, counted and said there
                if out is not None:
                    announced = self._emit(out, pipeline, bus, logger, announced)
            now = time.monotonic()
            if now - last_health >= 1.0:
                last_health = now
                health = {**source.counters.as_dict(), "processing_errors": self.processing_errors}
                bus.publish_health(health)
                if logger is not None:
                    logger.write_health(health)
                    self._say_recording_trouble(logger)

    def _emit(self, out, pipeline: Pipeline, bus, logger, announced: bool) -> bool:
        """Record and publish what processing a block gave; returns whether usability was announced."""
        if out.corrected is not None:
            if logger is not None:
                logger.write_corrected(out.corrected)
            bus.publish_corrected(out.corrected)
        if out.error:
            bus.publish_error(out.error)
        for ev in out.events:
            self._on_event(ev, pipeline, bus, logger)
            if ev.kind == "calibration" and not announced:
                announced = True
                self.say("calibration usable: corrected output is being published")
        return announced

    def _on_event(self, ev: PipelineEvent, pipeline: Pipeline, bus, logger) -> None:
        state = pipeline.state()
        record = {"kind": ev.kind, "seq": ev.seq, "t_s": ev.t_s, **ev.detail}
        if logger is not None:
            logger.write_calibration({**record, "state": state})
        bus.publish_calibration({**record, "state": state})
        if ev.kind == "calibration" and pipeline.calibration is not None:
            try:
                save_calibration(pipeline.calibration, self.cal_path)
            except OSError as e:
                self.say(f"could not persist the calibration to {self.cal_path}: {e}")
        elif ev.kind == "gate":
            log.info("gate: %s", "; ".join(ev.detail.get("reasons", [])))

    def _apply_command(self, cmd, pipeline: Pipeline, bus, logger) -> None:
        seq = pipeline.next_seq            # the command takes effect from the next block on
        try:
            payload = cmd.payload
            if cmd.name == "apply":
                payload = _calibration_from_payload(payload)
            ev = pipeline.command(cmd.name, payload, seq=seq, t_s=float("nan"))
            if cmd.name == "apply":
                from service.io.calfile import calibration_to_dict

                ev.detail["calibration"] = calibration_to_dict(payload)
            if logger is not None:
                logger.write_event({"kind": "command", "seq": seq, **ev.detail})
            self._on_event(ev, pipeline, bus, logger)
            cmd.reply({"ok": True, "cal_id": pipeline.cal_id})
        except FluxcalError as e:
            cmd.reply({"ok": False, "error": str(e)})


def _calibration_from_payload(payload: Any):
    from service.io.calfile import calibration_from_json

    if isinstance(payload, (bytes, bytearray)):
        payload = payload.decode("utf-8")
    text = str(payload).strip()
    if text.startswith("{"):
        return calibration_from_json(text, origin="zenoh command")
    return load_calibration(text)
