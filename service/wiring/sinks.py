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
from fluxcal.service.numerics.outputs import CorrectedBlock

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

    def _tell(self, method: str, *args: Any, **kwargs: Any) -> None:
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
        self._tell("on_flush")

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
    """Raw and corrected streams, errors, events, commands and health to rotating MCAP files (fluxcal.service.io.recordings)."""

    name = "recording"

    def __init__(self, logger: McapLogger) -> None:
        self.logger = logger

    @classmethod
    def open(cls, cfg: FluxcalConfig, calibration: Any, say: Callable[[str], None]) -> "McapSink | None":
        """The recording of [mcap] (None when disabled), with the calibration the run starts from as its first
        event; ConfigError naming mcap.dir when nothing can be recorded there."""
        logger = open_logger(cfg, calibration, say)
        return None if logger is None else cls(logger)

    def on_raw(self, block: SampleBlock) -> None:
        self.logger.write_raw(block)

    def on_corrected(self, block: CorrectedBlock) -> None:
        self.logger.write_corrected(block)

    def on_error(self, rms_nT: Mapping[str, float], *, seq: int, t_s: float, n: int) -> None:
        self.logger.write_error(dict(rms_nT), seq=seq, t_s=t_s, n=n)

    def on_event(self, record: Mapping[str, Any]) -> None:
        self.logger.write_calibration(dict(record))

    def on_command(self, record: Mapping[str, Any]) -> None:
        self.logger.write_event(dict(record))

    def on_health(self, counters: Mapping[str, Any], faults: Mapping[str, Any] | None) -> None:
        self.logger.write_health(dict(counters), faults=None if faults is None else dict(faults))

    def status(self) -> dict[str, Any]:
        return self.logger.status()

    def close(self) -> None:
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
