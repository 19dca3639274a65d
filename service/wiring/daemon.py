"""The long-running service: source -> pipeline -> Zenoh and MCAP, with reconnects and clean stops.

One thread does all the work (the MCAP writer is not thread-safe and the pipeline is stateful);
Zenoh callbacks only enqueue commands, drained here between blocks. SIGINT/SIGTERM set the stop
event; everything is flushed and closed in `finally`.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError, FluxcalError
from fluxcal.drivers.registry import source_kind
from fluxcal.drivers.source import Source
from fluxcal.drivers.text import printable

from .config import RATE_MISSING, FluxcalConfig
from .faults import FaultWatch
from .input import BatchReader, RateCheck, Reconnecting
from .pipeline import Pipeline, PipelineEvent
from .sinks import BusSink, McapSink, Sink, Sinks, say_bus
from .startcal import Keeper, initial_calibration
from .status import StatusLog


def build_pipeline(cfg: FluxcalConfig, initial=None) -> Pipeline:
    from fluxcal.service.wiring.user_effects import load_installed_effects, resolve_effects

    # effects of your own, registered before anything (a recorded add-effect, a calibration) names them
    load_installed_effects()
    try:
        resolve_effects(list(cfg.effects.plugins))
    except ConfigError as e:
        raise ConfigError(f"{cfg.path}: effects.plugins: {str(e).removeprefix('--effects: ')}") from None
    est = cfg.estimator
    positions = np.asarray(cfg.positions_m, float)
    has_geometry = cfg.unit.n_probes > 1 and np.ptp(positions, axis=0).any()
    rate = cfg.rate_hz
    if rate is None:
        raise ConfigError(f"{cfg.path}: {RATE_MISSING}")
    pl = Pipeline(n_probes=cfg.unit.n_probes, probe_names=cfg.probe_names,
                  positions_m=positions if has_geometry else None, forgetting=est.forgetting,
                  total_nT=est.total_nT, align=est.align, min_samples=est.min_samples,
                  gate_coverage=est.gate_coverage, gate_condition=est.gate_condition,
                  gate_rms_nT=est.gate_rms_nT, check_every_samples=max(1, int(round(est.check_every_s * rate))),
                  window_samples=int(est.window_s * rate), chunk_samples=max(1, int(round(est.update_every_s * rate))),
                  initial=initial)
    # a calibration applied by command stays until `reset`, across a restart (and in its replay) too
    pl.held = initial is not None and bool(initial.diagnostics.get("applied"))
    return pl


#: the bus's counters FaultWatch says beside the source's
BUS_COUNTED = ("send_stalls", "duplicate_holders")


def renamed(cfg: FluxcalConfig, name: str, note: Callable[[str], None], keeper: Keeper) -> Pipeline:
    """Serve under the name the bus took (unit.duplicate = "suffix"): the calibration persists under it too (two
    services never share one state file: the second would be refused it), and the pipeline starts from that name's."""
    kind = cfg.source.kind
    default = Path(cfg.calibration.file)
    if default.name == f"{cfg.unit.name}-{kind}-cal.json":
        cfg.calibration.file = str(default.with_name(f"{name}-{kind}-cal.json"))
    else:
        cfg.calibration.file = str(default.with_name(f"{default.stem}-{name}{default.suffix}"))
        note(f"the calibration persists in {cfg.calibration.file} (calibration.file with the name served under)")
    cfg.unit.name = name
    keeper.calibrations_refused = 0                 # what was refused was the other name's
    return build_pipeline(cfg, initial_calibration(cfg, note, refused=keeper.refused))


def open_configured_source(cfg: FluxcalConfig) -> Source:
    """The configured source, opened as its kind's declaration says (drivers/kinds/, fluxcal.drivers.registry)."""
    return source_kind(cfg.source.kind).open(cfg)


def open_outputs(sinks: Sinks, cfg: FluxcalConfig, calibration: Any, bus: Any, note: Callable[[str], None],
                 say: Callable[[str], None], extra: Sequence[Sink]) -> None:
    """The service's outputs into `sinks`, the recording first (a raw block is kept before anything else): each is
    among the sinks, and so closed with them, as soon as it is open, whichever opens next fails (the bus closes
    twice harmlessly)."""
    from fluxcal.service.wiring.ros2_sink import Ros2BagSink

    sinks.add(McapSink.open(cfg, calibration, note))
    sinks.add(BusSink(bus))
    sinks.add(Ros2BagSink.live(cfg, say))
    for sink in extra:
        sinks.add(sink)


def _say(msg: str) -> None:
    """A line on stderr with the UTC time: a field log is read afterwards, next to the recording. When whatever
    read stderr has gone (`fluxcal run ... 2>&1 | head -3`, a closed terminal), the service goes on: the lines
    go to /dev/null from then on, and the health channel and the recording still say everything."""
    try:
        print(f"fluxcal {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}: {printable(msg)}",   # a payload's
              file=sys.stderr, flush=True)        # or a peer's words never act on the terminal nor make lines
    except (OSError, ValueError):        # BrokenPipeError; ValueError: stderr closed
        stderr_gone()


def stderr_gone() -> None:
    """Point file descriptor 2 at /dev/null, so that neither the next line nor the interpreter's flush at exit
    fails on a reader that went away."""
    try:
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, sys.stderr.fileno())
        os.close(fd)
    except (OSError, ValueError, AttributeError):
        sys.stderr = open(os.devnull, "w")      # noqa: SIM115 - stays open for the process's life


class Processing:
    """pipeline.process, but an error in it (a bug meeting data nobody foresaw) costs that block's corrected output,
    never the service: it is counted (`errors`, the health's processing_errors), said (at most every 10 s, with the
    first sample's seq) and the next block is processed. Replay meets the same error at the same block."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say = say
        self.errors = 0                       # blocks whose processing raised (their raw data are kept)
        self._last_say = -1e9

    def __call__(self, pipeline: Pipeline, block: SampleBlock):
        try:
            return pipeline.process(block)
        except Exception as e:          # noqa: BLE001 - a long-running service must outlive one bad block
            self.errors += 1
            now = time.monotonic()
            if now - self._last_say >= 10.0:
                self._last_say = now
                seq0 = int(block.seq[0]) if block.n_samples else -1
                self.say(f"processing failed for the block from seq {seq0} ({block.n_samples} samples): "
                         f"{type(e).__name__}: {e}; its raw samples are recorded, its corrected output is "
                         f"lost; {self.errors} such block(s) so far (health: processing_errors)")
            return None


class Daemon:
    """`fluxcal run`: wires a source, the pipeline and the sinks (the MCAP recording, the Zenoh bus, any others)."""

    def __init__(self, cfg: FluxcalConfig, *, stop: threading.Event | None = None,
                 say: Callable[[str], None] | None = None, sinks: Sequence[Sink] = ()) -> None:
        """`sinks`: outputs besides the recording and the bus (fluxcal.service.wiring.sinks.Sink), told after them."""
        self.cfg = cfg
        self.stop = stop or threading.Event()
        self.say = say or _say
        self.extra_sinks = list(sinks)
        self._reader = BatchReader(cfg.unit.block_ms, self.stop)
        self._link = Reconnecting(self._reader, self.stop, self.say)   # counts the input's losses and returns
        self._process = Processing(self.say)  # a block whose processing raises costs its output only
        self.keeper = Keeper(cfg, self.say)   # the calibrations refused, and the saves of the one in use
        self._faults = FaultWatch(self.say, silence_s=cfg.unit.silence_s, every_s=cfg.unit.status_s)
        self._rate = RateCheck(cfg, self.say)
        self._status = StatusLog(self.say, cfg.unit.status_s)

    def run(self) -> int:
        from fluxcal.service.io.bus import ServiceBus

        cfg = self.cfg
        notes: list[str] = []                 # said once the source, the bus and the recording are open
        pipeline = build_pipeline(cfg, initial_calibration(cfg, notes.append, refused=self.keeper.refused))
        source = open_configured_source(cfg)
        self._faults.words = source.counters.words        # what its counters are said in: its bus's words
        sinks = Sinks([], self.say)           # the recording first: a raw block is kept before anything else
        bus = None
        try:
            bus = ServiceBus(cfg.zenoh, unit=cfg.unit.name, probe_names=cfg.probe_names,
                             state_fn=lambda: self._state(pipeline, source, sinks), duplicate=cfg.unit.duplicate,
                             config=cfg.path)
            if bus.unit != cfg.unit.name:                  # unit.duplicate = "suffix": another holds the name
                notes = [bus.claim_note]
                pipeline = renamed(cfg, bus.unit, notes.append, self.keeper)
            self.keeper.claim()               # calibration.file (the name's, once it is known) is this service's
            open_outputs(sinks, cfg, pipeline.calibration, bus, notes.append, self.say, self.extra_sinks)
            for note in notes:
                self.say(note)
            say_bus(cfg, self.say)
            self._loop(source, pipeline, sinks)
            failed = False
        except BaseException:
            failed = True
            raise
        finally:
            self._summary(source, sinks)
            for closer in (source.close, sinks.close, getattr(bus, "close", None), self.keeper.release):
                if closer is not None:
                    try:
                        closer()
                    except Exception as e:  # closing must never hide the first error
                        self.say(f"while closing: {e}")
            self.say("stopped (the reason follows)" if failed else "stopped")
        return 0

    @property
    def rate_checked(self) -> bool:
        """Whether the unit clock has been compared with the configured rate (input.RateCheck)."""
        return self._rate.checked

    def _state(self, pipeline: Pipeline, source: Source, sinks: Sinks) -> dict[str, Any]:
        st = pipeline.state()
        st["health"] = self._health(source, sinks)
        st["faults"] = self._faults.health()
        st["source"] = {"kind": self.cfg.source.kind, "protocol": getattr(self.cfg.source, "protocol", ""),
                        "counters": source.counters.words.about()}         # what its health counters count
        if (recording := sinks.recording()) is not None:
            st["recording"] = recording
        return st

    def _health(self, source: Source, sinks: Sinks) -> dict[str, Any]:
        """The health channel's counters: the source's own (its declaration's), the input's losses, what the service
        refused or failed to process, and the messages an output failed to take: all outputs', and each failing
        output's own (`output_failures.<name>`, shown beside the others by the dashboard and the summary at stop)."""
        return {**source.counters.as_dict(), **self._link.counts(), "processing_errors": self._process.errors,
                "commands_refused": self._status.refused, "output_failures": sum(sinks.errors.values()),
                **self.keeper.counts(),
                **{f"output_failures.{name}": n for name, n in sinks.errors.items() if n}}

    def _tick_health(self, source: Source, sinks: Sinks, bus, final: bool = False) -> None:
        """The health counters and the faults to every sink; at stop (final), with the summary of the run said."""
        health = self._health(source, sinks)
        counted = {**health, **{k: int(getattr(bus, "stats", {}).get(k, 0)) for k in BUS_COUNTED}}
        faults = self._faults.tick(counted, sinks.recording(), self._link.down_why)
        if final:
            faults["summary"] = self._faults.summary(counted, sinks.recording(), outputs=sinks.errors)
            for line in faults["summary"]:
                self.say(line)
        sinks.health(health, faults)

    def _summary(self, source: Source, sinks: Sinks) -> None:
        """At stop: every loss and fault of the run with its count, said and sent as the last health message
        (nothing when the service stopped before its loop began: it read nothing)."""
        if not self._faults.started:
            return
        try:
            bus = next((s.bus for s in sinks.sinks if isinstance(s, BusSink)), None)
            self._tick_health(source, sinks, bus, final=True)
        except Exception as e:  # noqa: BLE001 - the summary must never hide why the service stopped
            self.say(f"while summarising: {type(e).__name__}: {e}")

    def _loop(self, source: Source, pipeline: Pipeline, sinks: Sinks) -> None:
        bus = next(s.bus for s in sinks.sinks if isinstance(s, BusSink))       # commands come from it too
        link = self._link
        last_health, announced = 0.0, pipeline.calibration is not None
        while not self.stop.is_set():
            for cmd in bus.pending_commands():
                self._apply_command(cmd, pipeline, sinks)
            sinks.flush()                     # what waits (commands' events, health) goes out before the wait for input
            block = link.read(source)         # None while the input is down: health still goes out
            if link.stopped:
                break
            if block is None:
                if source.exhausted:
                    self.say("source exhausted")
                    break
            else:
                announced = self._take(block, pipeline, sinks, announced)
            now = time.monotonic()
            if now - last_health >= 1.0:
                last_health = now
                self._status.bus_refusals(bus)
                self._status.holders(bus)
                self._tick_health(source, sinks, bus)
                self._status.tick(pipeline.state(), self._faults.active())

        held = source.drain()                 # what the source holds that no more input completes: not lost
        if held is not None:
            self._take(held, pipeline, sinks, announced)

    def _take(self, block: SampleBlock, pipeline: Pipeline, sinks: Sinks, announced: bool) -> bool:
        """One block read: recorded and published raw first, then processed and its outputs emitted; returns whether
        usability was announced."""
        if not self.rate_checked:
            self._rate.check(block)
        sinks.raw(block)                      # kept and published first: whatever happens to its processing
        out = self._process(pipeline, block)  # None: failed, counted and said there
        if out is not None:
            self._status.block(block.n_samples, out.error)
            announced = self._emit(out, pipeline, sinks, announced)
        return announced

    def _emit(self, out, pipeline: Pipeline, sinks: Sinks, announced: bool) -> bool:
        """Record and publish what processing a block gave; returns whether usability was announced."""
        if out.corrected is not None:
            sinks.corrected(out.corrected)
            if out.error:
                c = out.corrected
                sinks.error(out.error, seq=int(c.seq[0]), t_s=float(c.t_s[0]), n=c.n_samples)
        for ev in out.events:
            self._on_event(ev, pipeline, sinks)
            if ev.kind == "calibration" and not announced:
                announced = True
                self.say("calibration usable: corrected output is being published")
        sinks.flush()                         # the block's messages go out together, before any later command's
        return announced

    def _on_event(self, ev: PipelineEvent, pipeline: Pipeline, sinks: Sinks) -> None:
        sinks.event({"kind": ev.kind, "seq": ev.seq, "t_s": ev.t_s, **ev.detail, "state": pipeline.state()})
        name = ev.detail.get("name") if ev.kind == "command" else None     # after a reset, no longer held: persisted
        if (ev.kind == "calibration" or name in ("apply", "reset")) and pipeline.calibration is not None:
            self.keeper.persist(pipeline.calibration, name == "apply")
        if ev.kind == "data check":                   # the calibration started from fails it: said, counted
            self.keeper.doubted += 1
            self.say(f"{ev.detail['reasons'][0]} (health: calibrations_doubted)")
        if ev.kind in ("gate", "calibration"):
            self._status.gate(ev.kind == "calibration" or bool(ev.detail.get("usable")), ev.detail.get("reasons", []))

    def _apply_command(self, cmd, pipeline: Pipeline, sinks: Sinks) -> None:
        """Apply one command between blocks and answer it. Whatever the payload, the answer is ok or a refusal
        with its reason: an exception of any kind is a refusal, counted and said, never the service's end."""
        seq = pipeline.next_seq            # the command takes effect from the next block on
        try:
            payload = cmd.payload
            if cmd.name == "apply":
                payload = self.keeper.to_apply(payload, pipeline)
            ev = pipeline.command(cmd.name, payload, seq=seq, t_s=float("nan"))
            if cmd.name == "apply":
                from fluxcal.service.io.calfile import calibration_to_dict

                ev.detail["calibration"] = calibration_to_dict(payload)
            sinks.command({"kind": "command", "seq": seq, **ev.detail})
            self._on_event(ev, pipeline, sinks)
            answer = {"ok": True, "cal_id": pipeline.cal_id}
        except FluxcalError as e:
            answer = {"ok": False, "error": str(e)}
        except Exception as e:  # noqa: BLE001 - no payload can stop the service
            answer = {"ok": False, "error": f"{cmd.name}: not applied: {type(e).__name__} while taking the command "
                                            f"(a fault of fluxcal's, not of the payload's: please report it)"}
        try:
            cmd.reply(answer)
        except Exception as e:  # noqa: BLE001 - the client went away: the answer is said below anyway
            self.say(f"command {cmd.name}: the answer could not be sent: {type(e).__name__}")
        self._status.command(cmd.name, cmd.payload, answer)
