"""The simulated unit as a Source (its kind is declared in drivers/kinds/sim.py).

In process (its own transport, the default): SampleBlocks straight from the world, exactly what a
decoder of the unit's frames would yield (NaN where saturated or temperature-invalid, t_s from the
unit clock) plus extras["ref_total"] when the scalar reference is enabled. Wire faults do not apply
(there is no wire); flagged samples do.

Through a transport another kind declares (fluxcal.drivers.registry.transports(): a pty, a CAN bus): the unit streams
through that transport's emitter (fluxcal.drivers.sim.ports, can_ports) and the kind's real driver reads it, so the whole
driver path runs, with that kind's counters; ref_total is not on the wire and is absent then.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

from ..block import FLAG_TEMP_INVALID, SampleBlock
from ..config import spec
from ..declare import SourceTable, resolve
from ..errors import ConfigError
from ..kinds.sim import KIND
from ..registry import source_kind
from ..registry import transport as registry_transport
from ..source import Counters, Source
from .config import SimConfig
from .unit import Unit
from .world import World


class SimSource(Source):
    """SampleBlocks from the simulated world, paced by the wall clock (realtime) or as fast as read.

    >>> from fluxcal.drivers.sim.config import load_sim_config
    >>> src = SimSource(load_sim_config({"duration_s": 1.0, "rate_hz": 100.0}), block_s=0.5)
    >>> [len(src.read()), len(src.read()), src.read(), src.exhausted]
    [50, 50, None, True]
    """

    def __init__(self, config: SimConfig, *, realtime: bool | None = None, block_s: float = 0.05,
                 max_block_s: float = 1.0, start_index: int = 0) -> None:
        super().__init__(config.n_probes, Counters.of(source_kind(KIND.name).words()))
        self.config = config
        self.unit = Unit(config)
        self.world: World = self.unit.world
        self.realtime = config.realtime if realtime is None else bool(realtime)
        self.rate_hz = config.rate_hz
        self._pace_hz = config.rate_hz * config.speed       # samples per second of the wall clock (realtime)
        self.block_n = max(1, int(round(block_s * self.rate_hz)))
        self.max_block_n = max(self.block_n, int(round(max_block_s * self.rate_hz)))
        self.next_index = start_index
        # the unit runs from the moment it is opened: sample i exists at t0 + i / rate_hz
        self._t0 = time.monotonic() - start_index / self._pace_hz

    @property
    def exhausted(self) -> bool:
        n = self.unit.n_samples
        return n is not None and self.next_index >= n

    def truth(self) -> dict[str, Any]:
        return self.world.truth()

    def _read_block(self, timeout: float | None) -> SampleBlock | None:
        n = self.unit.n_samples
        if self.exhausted:
            return None
        start = self.next_index
        if self.realtime:
            deadline = None if timeout is None else time.monotonic() + timeout
            while True:
                due = math.floor((time.monotonic() - self._t0) * self._pace_hz) + 1   # samples 0..due-1 exist
                if due > start:
                    break
                wake = self._t0 + start / self._pace_hz
                if deadline is not None:
                    if time.monotonic() >= deadline:
                        return None
                    wake = min(wake, deadline)
                time.sleep(max(0.0, wake - time.monotonic()))
            stop = min(due, start + self.max_block_n)
        else:
            stop = start + self.block_n
        if n is not None:
            stop = min(stop, n)
        s = self.unit.digitise(start, stop)
        self.next_index = stop
        c = self.counters
        c.frames_accepted += len(s)
        c.saturated_axes += int(s.saturated.sum())
        c.temp_invalid += int(((s.flags & FLAG_TEMP_INVALID) != 0).sum())
        return s.to_block()


class EmitterSource(Source):
    """A real driver source reading the simulated unit through an emitter it owns (pty, CAN, SLCAN)."""

    def __init__(self, inner: Source, emitter: Any) -> None:
        super().__init__(inner.n_probes, inner.counters)     # one set of counters: the driver's, with its words
        self.inner = inner
        self.emitter = emitter
        self._quiet_since: float | None = None

    @property
    def record(self) -> Any:
        """The emitter's FaultRecord: what was corrupted on purpose."""
        return self.emitter.record

    def drain(self) -> SampleBlock | None:
        """What the driver holds at the end (a CAN assembler's samples: released or counted)."""
        return self.inner.drain()

    #: after the emitter's last sample, this long without data means the run is over (the CAN
    #: assembler may hold samples up to its window_s behind an incomplete one)
    QUIET_AFTER_END_S = 1.0

    @property
    def exhausted(self) -> bool:
        return self._quiet_since is not None and time.monotonic() - self._quiet_since >= self.QUIET_AFTER_END_S

    def _read_block(self, timeout: float | None) -> SampleBlock | None:
        block = self.inner.read(timeout)
        if block is not None and len(block):
            self._quiet_since = None
        elif self.emitter.done.is_set() and self._quiet_since is None:
            self._quiet_since = time.monotonic()
        return block

    def reopen(self) -> None:
        self.inner.reopen()

    def truth(self) -> dict[str, Any]:
        return self.emitter.unit.world.truth()

    def close(self) -> None:
        if not self._closed:
            try:
                self.inner.close()
            finally:
                self.emitter.close()
        super().close()


@dataclass(kw_only=True)
class SimSourceConfig(SourceTable):
    """The [source] table of the simulated unit."""

    transport: str = spec("", doc="how the simulated unit reaches the service: any simulator transport of "
                                  "docs/sources.md (empty: the first, in process); another kind's is read by that "
                                  "kind's driver, with its counters")
    run_s: float = spec(0.0, min=0.0, max=1.0e9,
                        doc="how long `fluxcal run` lets the simulated unit run; 0 = until stopped "
                            "(`fluxcal simulate` uses sim.duration_s)")

    def validate(self, path: str) -> None:
        self.transport = registry_transport(self.transport or KIND.transports[0].name, f"{path}.transport")[1].name


def open_source(config: Any, *, unit: Any = None, transport: str = "", realtime: bool | None = None,
                block_s: float = 0.05, **kwargs: Any) -> Source:
    """Open the simulated unit as a Source.

    config: a SimConfig, or the whole service configuration (anything with a .sim SimConfig, and
    optionally .unit and .source.transport). unit: the [unit] section (n_probes and lsb_nT are checked
    against the simulation). transport: a name fluxcal.drivers.registry.transports() gives (empty: in process). Other
    keyword arguments go to the transport's emitter (e.g. link_dir, channel)."""
    if not isinstance(config, SimConfig):
        full = config
        config = getattr(full, "sim", None)
        if not isinstance(config, SimConfig):
            raise ConfigError("sim: the configuration has no [sim] section for the simulated unit")
        unit = unit if unit is not None else getattr(full, "unit", None)
        transport = transport or getattr(getattr(full, "source", None), "transport", "")
    if unit is not None:
        n = getattr(unit, "n_probes", config.n_probes)
        if n != config.n_probes:
            raise ConfigError(f"sim.probes: {config.n_probes} simulated probes but unit.n_probes = {n}")
        lsb = getattr(unit, "lsb_nT", config.lsb_nT)
        if not math.isclose(lsb, config.lsb_nT, rel_tol=1e-12):
            raise ConfigError(f"sim.lsb_nT: {config.lsb_nT!r} differs from unit.lsb_nT = {lsb!r}; "
                              f"the simulated unit and the driver must scale counts alike")
    kind, way = registry_transport(transport or KIND.transports[0].name)
    if way.link is None:
        return SimSource(config, realtime=realtime, block_s=block_s)
    u = Unit(config)
    emitter, table, options = resolve(way.link)(u, realtime=realtime, **kwargs)
    try:
        inner = kind.open_table(table, "source.transport", **options)
        if not emitter.done.is_set() and getattr(emitter, "_thread", None) is None:
            emitter.start()               # a virtual bus: start once the reader's bus exists
    except BaseException:
        emitter.close()
        raise
    return EmitterSource(inner, emitter)


def open_configured(cfg: Any) -> Source:
    """The simulated unit of the service's configuration: its [sim] world for [source] run_s, through
    [source] transport."""
    sim = dataclasses.replace(cfg.sim, duration_s=cfg.source.run_s)
    return open_source(sim, unit=cfg.unit, transport=cfg.source.transport)


__all__ = ["SimSource", "EmitterSource", "SimSourceConfig", "open_source", "open_configured"]
