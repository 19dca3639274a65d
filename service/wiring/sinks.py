"""The service's outputs behind one contract (python-can's Listener and Notifier are the model): a `Sink` is told,
on the service's thread and in order, of everything the loop produces; `Sinks` holds the list and tells each one.
The MCAP recording and the Zenoh bus are two sinks; a recording that is disabled is simply not in the list, and a
new output is one class (a test adds one that counts messages, without touching the daemon).

    on_raw(block)               every block as read from the unit, before it is processed
    on_corrected(block)         its corrected output, differences, centre and tensor
    on_error(rms_nT, seq, t_s, n)  the model-vs-measurement error of that output
    on_event(record)            a calibration replaced, a gate refusal, a command applied: with the state after it
    on_command(record)          a command as applied, for replay to apply again at its seq
    on_health(counters, faults) the counters and the faults (about once a second, and once at stop)
    on_flush()                  everything of this turn of the loop has been told: a sink that gathers its
                                messages sends them now (the bus: one wake-up of its sender per block)
    status()                    what the sink says of itself (a recorder: files, errors, drops), or None
    close()
"""

from __future__ import annotations

import json
import time
from typing import Any, Callable, Mapping

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError
from fluxcal.service.io.calfile import calibration_to_dict
from fluxcal.service.io.recordings.writer import McapLogger
from fluxcal.service.numerics.outputs import CorrectedBlock, join_corrected

from .config import FluxcalConfig


class Sink:
    """One output of the service. Every method does nothing unless a sink overrides it: a sink takes what it wants."""

    name = "sink"

    def on_raw(self, block: SampleBlock) -> None:
        pass

    def on_corrected(self, block: CorrectedBlock) -> None:
        pass

    def on_error(self, rms_nT: Mapping[str, float], *, seq: int, t_s: float, n: int) -> None:
        pass

    def on_event(self, record: Mapping[str, Any]) -> None:
        pass

    def on_command(self, record: Mapping[str, Any]) -> None:
        pass

    def on_health(self, counters: Mapping[str, Any], faults: Mapping[str, Any] | None) -> None:
        pass

    def on_flush(self) -> None:
        pass

    def status(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        pass


class Sinks:
    """The service's sinks, told in order. A sink that raises costs that message for that sink only: the others
    still get it, the failure is counted (`errors`, by sink) and said at most once a minute per sink."""

    def __init__(self, sinks: list[Sink], say: Callable[[str], None]) -> None:
        self.sinks = list(sinks)
        self.say = say
        self.errors: dict[str, int] = {s.name: 0 for s in self.sinks}
        self._said_at: dict[str, float] = {}
        self._told = False                # something was told since the last flush

    def _tell(self, method: str, *args: Any, **kwargs: Any) -> None:
        self._told = True
        for sink in self.sinks:
            try:
                getattr(sink, method)(*args, **kwargs)
            except Exception as e:  # noqa: BLE001 - one output's fault must not cost the others theirs
                self.errors[sink.name] = self.errors.get(sink.name, 0) + 1
                now = time.monotonic()
                if now - self._said_at.get(sink.name, -1e9) >= 60.0:
                    self._said_at[sink.name] = now
                    self.say(f"output {sink.name} failed on {method[3:]}: {type(e).__name__}: {e}; "
                             f"{self.errors[sink.name]} failure(s) so far (the other outputs carry on)")

    def raw(self, block: SampleBlock) -> None:
        self._tell("on_raw", block)

    def corrected(self, block: CorrectedBlock) -> None:
        self._tell("on_corrected", block)

    def error(self, rms_nT: Mapping[str, float], *, seq: int, t_s: float, n: int) -> None:
        self._tell("on_error", rms_nT, seq=seq, t_s=t_s, n=n)

    def event(self, record: Mapping[str, Any]) -> None:
        self._tell("on_event", record)

    def command(self, record: Mapping[str, Any]) -> None:
        self._tell("on_command", record)

    def health(self, counters: Mapping[str, Any], faults: Mapping[str, Any] | None) -> None:
        self._tell("on_health", counters, faults)

    def flush(self) -> None:
        """The end of a turn: every sink told on_flush, when anything was told since the last (a turn that read
        nothing and answered nothing costs no call)."""
        if self._told:
            self._tell("on_flush")
            self._told = False

    def recording(self) -> dict[str, Any] | None:
        """The recorder's status (the first sink that has one), for the state and the fault watch."""
        for sink in self.sinks:
            st = sink.status()
            if st is not None:
                return st
        return None

    def add(self, sink: Sink | None) -> None:
        """One more sink, told after those before it (None: an output that is disabled, not in the list)."""
        if sink is not None:
            self.sinks.append(sink)
            self.errors.setdefault(sink.name, 0)

    def close(self) -> None:
        """Close every sink in order; a failure is said and never hides the others' closing."""
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as e:  # noqa: BLE001 - closing must never hide the first error
                self.say(f"while closing {sink.name}: {e}")


class McapSink(Sink):
    """Raw and corrected streams, errors, events, commands and health to rotating MCAP files (fluxcal.service.io.recordings).

    The data streams are gathered: the blocks of about GATHER_S of unit time (and at most GATHER_WALL_S of the host
    clock) go into one raw and one corrected message, with their error metrics, written before any other record
    (an event, a command, health) and at close. A message costs the same whatever its samples, so the service's
    thread pays once a tenth of a second what it paid every block; replay does not depend on how its input was cut
    into messages (the pipeline's output does not depend on blocking). What is gathered waits in memory as the
    unfinished chunk does (mcap.flush_s): a stop writes it, only a killed process loses it."""

    name = "recording"
    #: unit time gathered into one raw and one corrected message, s (the 10 Hz products' interval)
    GATHER_S = 0.1
    #: host time the first gathered block waits at most, s (a slow unit's blocks are not held long)
    GATHER_WALL_S = 0.25

    def __init__(self, logger: McapLogger) -> None:
        self.logger = logger
        self._raw: list[SampleBlock] = []
        self._corrected: list[CorrectedBlock] = []
        self._errors: list[tuple[dict[str, float], int, float, int]] = []
        self._since = 0.0                 # host monotonic time of the first block gathered

    @classmethod
    def open(cls, cfg: FluxcalConfig, calibration: Any, say: Callable[[str], None]) -> "McapSink | None":
        """The recording of [mcap] (None when disabled), with the calibration the run starts from as its first
        event; ConfigError naming mcap.dir when nothing can be recorded there."""
        logger = open_logger(cfg, calibration, say)
        return None if logger is None else cls(logger)

    def on_raw(self, block: SampleBlock) -> None:
        if not block.n_samples:
            return
        if not self._raw:
            self._since = time.monotonic()
        self._raw.append(block)

    def on_corrected(self, block: CorrectedBlock) -> None:
        if self._corrected and block.cal_id != self._corrected[-1].cal_id:
            self.write_gathered()             # one calibration per message (the 10 Hz means end at its change too)
        self._corrected.append(block)

    def on_error(self, rms_nT: Mapping[str, float], *, seq: int, t_s: float, n: int) -> None:
        self._errors.append((dict(rms_nT), seq, t_s, n))

    def on_flush(self) -> None:
        """The end of a turn: the gathered blocks are written once they span GATHER_S (or waited GATHER_WALL_S)."""
        raw = self._raw
        if raw and (float(raw[-1].t_s[-1]) - float(raw[0].t_s[0]) >= self.GATHER_S
                    or time.monotonic() - self._since >= self.GATHER_WALL_S):
            self.write_gathered()

    def write_gathered(self) -> None:
        """What was gathered, as one raw and one corrected message and the error metrics, in that order."""
        raw, corrected, errors = self._raw, self._corrected, self._errors
        self._raw, self._corrected, self._errors = [], [], []
        if raw:
            self.logger.write_raw(raw[0] if len(raw) == 1 else SampleBlock.concat(raw))
        if corrected:
            self.logger.write_corrected(corrected[0] if len(corrected) == 1 else join_corrected(corrected))
        for rms_nT, seq, t_s, n in errors:
            self.logger.write_error(rms_nT, seq=seq, t_s=t_s, n=n)

    def on_event(self, record: Mapping[str, Any]) -> None:
        self.write_gathered()
        self.logger.write_calibration(dict(record))

    def on_command(self, record: Mapping[str, Any]) -> None:
        self.write_gathered()
        self.logger.write_event(dict(record))

    def on_health(self, counters: Mapping[str, Any], faults: Mapping[str, Any] | None) -> None:
        self.write_gathered()
        self.logger.write_health(dict(counters), faults=None if faults is None else dict(faults))

    def status(self) -> dict[str, Any]:
        return self.logger.status()

    def close(self) -> None:
        try:
            self.write_gathered()
        finally:
            self.logger.close()


class BusSink(Sink):
    """The streams published on Zenoh (fluxcal.service.io.bus.ServiceBus); the bus also takes commands and state queries,
    which the daemon reads from it directly. What a turn of the loop publishes goes out together at its on_flush."""

    name = "bus"

    def __init__(self, bus: Any) -> None:
        self.bus = bus
        bus.gather_sends()

    def on_raw(self, block: SampleBlock) -> None:
        self.bus.publish_raw(block)

    def on_corrected(self, block: CorrectedBlock) -> None:
        self.bus.publish_corrected(block)

    def on_error(self, rms_nT: Mapping[str, float], *, seq: int, t_s: float, n: int) -> None:
        self.bus.publish_error(rms_nT, seq=seq, t_s=t_s, n=n)

    def on_event(self, record: Mapping[str, Any]) -> None:
        self.bus.publish_calibration(record)

    def on_health(self, counters: Mapping[str, Any], faults: Mapping[str, Any] | None) -> None:
        self.bus.publish_health(counters, faults=faults)

    def on_flush(self) -> None:
        self.bus.send()

    def close(self) -> None:
        self.bus.close()


def open_logger(cfg: FluxcalConfig, calibration: Any, say: Callable[[str], None]) -> McapLogger | None:
    """The MCAP logger of [mcap] (None when disabled), with the calibration the run starts from as its first
    event; ConfigError naming mcap.dir when nothing can be recorded there."""
    if not cfg.mcap.enabled:
        return None
    logger = McapLogger(cfg.mcap.dir, unit=cfg.unit.name, rotate_mb=cfg.mcap.rotate_mb,
                        rotate_s=cfg.mcap.rotate_s, chunk_size=cfg.mcap.chunk_kb * 1024,
                        flush_interval_s=cfg.mcap.flush_s,
                        metadata={"unit": cfg.unit.name, "n_probes": str(cfg.unit.n_probes),
                                  "lsb_nT": repr(cfg.unit.lsb_nT),
                                  "probe_names": json.dumps(cfg.probe_names),
                                  "positions_m": json.dumps(cfg.positions_m),
                                  "config": json.dumps(cfg.raw)})
    # replay starts from the same calibration, so it reproduces this run bit for bit
    logger.write_event({"kind": "initial", "seq": 0, "calibration":
                        None if calibration is None else calibration_to_dict(calibration)})
    st = logger.status()
    if st["current"] is None:
        logger.close()
        # nothing could be opened: say so now, not after a day of data that went nowhere
        raise ConfigError(f"mcap.dir: {str(cfg.mcap.dir)!r}: cannot record there: {st['last_error']} "
                          f"(allowed: a directory this user can create and write into; or set "
                          f"[mcap] enabled = false to run without recording)")
    say(f"recording to {cfg.mcap.dir}/")
    return logger


def say_bus(cfg: FluxcalConfig, say: Callable[[str], None]) -> None:
    """Where the service publishes, and a warning for every endpoint other hosts reach in clear text."""
    say(f"publishing on zenoh under fluxcal/{cfg.unit.name}/ "
        f"(listen {', '.join(getattr(cfg.zenoh, 'listen', []) or ['-'])}"
        f"{', TLS' if cfg.zenoh.tls.enabled else ''}"
        f"{', access control' if cfg.zenoh.access.enabled else ''})")
    for ep in cfg.zenoh.exposed():
        say(f"warning: {ep} is reachable from other hosts in clear text and without access control: "
            f"anyone on that network can read the streams and send commands (docs/security.md)")
