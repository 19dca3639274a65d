"""What an input is, declared once: a source kind's [source] table, its factory, its clock and rate rules, the
[source] keys the service names when its port will not open, the simulator's transports that feed it, its
protocols, and its counters with the words the service says about each. The declarations of fluxcal's own kinds
are the modules of drivers/kinds/; fluxcal.drivers.registry finds them (and those of installed packages and of code that
registers its own) and every other part of fluxcal reads them there: nothing else names a kind.

    SourceKind      one kind of input (a serial port, a CAN bus, ...): how its table is read and its source opened
    Protocol        one way the unit's bytes or frames become samples on a kind (the ICD's frames, ...)
    Transport       one way the simulated unit reaches the service through a kind (a pty, a virtual CAN bus)
    Counted         one counter and what is said about it; Words, the counters of one kind and protocol
    NoDecode        what is said when input arrives but nothing of the unit's decodes
    SourceTable     the base of every kind's [source] table (kind; ProtocolTable adds protocol)

A declaration is data and names its code as "module:attribute" (imported when the kind is used, like python-can's
interfaces) or holds the object itself (a test's or a user's kind).
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass
from typing import Any, Callable

from .config import load_section, spec
from .errors import ConfigError, DriverError


def resolve(target: Any) -> Any:
    """The object a declaration names: "module:attribute" imported now, anything else as it is."""
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True)
class Counted:
    """A counter of an input, and what the service says about it (service/wiring/faults.py says the lines,
    docs/sources.md lists them). `what` and `label` are said only for a counter with a `fault` name."""

    name: str                 # the counter, in health.counters: "crc_failures"
    doc: str                  # what it counts, in its bus's words
    fault: str = ""           # its name in health.faults when its growth is said ("crc"); "" = a figure only
    label: str = ""           # what a line about it starts with: "CRC failures"
    what: str = ""            # what {n} of it are: "{n:,} frame(s) failed their CRC"
    advice: str = ""          # what to check
    one_shot: bool = False    # said each time it counts (a restart), never as begun or ended
    quiet: bool = False       # said where it happens (a refused command): here only counted and summarised
    arrival: bool = False     # its growth means something came from the port or bus: no silence then
    decoded: bool = False     # ... the unit's own frames, decoded: the run's throughput (the summary's head)
    share: str = ""           # said with its share of it and the decoded counter: " (4% of the frames)" -> "frames"
    beside: tuple[tuple[str, str], ...] = ()   # counters said beside it: (("seq_gaps", "{n:,} gap(s)"),)


@dataclass(frozen=True)
class NoDecode:
    """What is said when input arrives (the arrival counters grow) but none of it decodes into the unit's frames
    for a while: `arrives` names the input ("bytes": health.faults.totals.no_decode_bytes counts it)."""

    arrives: str
    begin: str        # "... {n:,} bytes in {t}, 0 frames; check ...": {n} the input, {t} how long
    end: str          # "frames decode again after {t}; {n:,} bytes in between decoded into no frame"
    total: str        # "{k} stretch(es) of bytes that decoded into no frame ({n:,} bytes)"
    label: str = "no frame decodes"


@dataclass(frozen=True)
class Words:
    """The counters of one input (a kind and its protocol), each with its words: what Counters holds."""

    counted: tuple[Counted, ...]
    no_decode: NoDecode | None = None

    def __post_init__(self) -> None:
        names = [c.name for c in self.counted]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ConfigError(f"counters {', '.join(twice)} declared twice for one input (allowed: each once)")
        bad = [n for n in names if not n.isidentifier() or n.startswith("_")]
        if bad:
            raise ConfigError(f"counter names {bad} are not allowed (allowed: identifiers not starting with _)")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.counted)

    def named(self, name: str) -> Counted | None:
        return next((c for c in self.counted if c.name == name), None)

    @property
    def arrival(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.counted if c.arrival or c.decoded)

    @property
    def decoded(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.counted if c.decoded)

    def about(self) -> dict[str, dict[str, Any]]:
        """Each counter's words for a reader (the state reply, the dashboard's health table): what it counts,
        whether it counts what arrives (no fault however large), and the fault it is said as."""
        return {c.name: {"doc": c.doc, "flow": (c.arrival or c.decoded) and not c.fault, "fault": c.fault}
                for c in self.counted}


@dataclass(frozen=True)
class Protocol:
    """One way a kind's bytes or frames become the unit's samples. `decoder` is what the kind's source builds to
    decode them: its interface is the kind's (fluxcal.drivers.serial_source.SerialSource: `feed(data, rx_time_s)` and
    `discard_tail()`; fluxcal.drivers.can_source.CanSource: `decode(messages, now_s)` and `finish()`, what it holds
    at the end of input)."""

    name: str
    doc: str
    decoder: Any = None
    counters: tuple[Counted, ...] = ()
    no_decode: NoDecode | None = None
    unit_clock: bool | None = None     # the samples' time is the unit's own clock; None: as the kind says
    kind: str = ""                     # declared apart from its kind (an entry point): the kind it belongs to


@dataclass(frozen=True)
class Transport:
    """One way the simulated unit reaches the service through a kind: `link(unit, realtime=..., **options)` starts
    its emitter and returns (emitter, the kind's [source] table that reads it, the factory's keyword options);
    None: the simulated unit's own samples, in process."""

    name: str
    doc: str
    link: Any = None
    process: bool = False              # it can serve another process (`python -m fluxcal.drivers.sim --transport NAME`)


@dataclass(kw_only=True)
class SourceTable:
    """The base of every kind's [source] table: the key that chose it."""

    kind: str = spec("", doc="the source kind (docs/sources.md)")


@dataclass(kw_only=True)
class ProtocolTable(SourceTable):
    """The base of the [source] table of a kind with protocols."""

    protocol: str = spec("", doc="how the unit's bytes or frames become samples; empty: the kind's first protocol")


@dataclass(frozen=True)
class SourceKind:
    """One kind of input, everything about it in one place (the module docstring).

    config       its [source] table: a dataclass deriving SourceTable (ProtocolTable when it has protocols)
    factory      factory(table, **options) -> Source (fluxcal.drivers.source.open_source(kind, ...) calls it)
    opener       opener(configuration) -> Source, from the whole service configuration (its .source, .unit,
                 .sim); None: factory(configuration.source)
    counters     the kind's own counters (its port or bus), beside each protocol's
    port_keys    the [source] keys a failure to open names, before the driver's own words
    path_keys    [source] keys that are paths, taken relative to the configuration file
    unit_clock   the samples' time is the unit's own clock: the configured rate is checked against it once
    needs_rate   the configuration must state the unit's rate (source.rate_hz, or [sim] rate_hz)
    runs_world   it runs the [sim] world (read with its defaults even without a [sim] section)
    default      the kind of a configuration that names none (one a recording of an older run stores)
    """

    name: str
    doc: str
    config: Any
    factory: Any
    opener: Any = None
    counters: tuple[Counted, ...] = ()
    protocols: tuple[Protocol, ...] = ()
    transports: tuple[Transport, ...] = ()
    no_decode: NoDecode | None = None
    port_keys: tuple[str, ...] = ()
    path_keys: tuple[str, ...] = ()
    unit_clock: bool = True
    needs_rate: bool = False
    runs_world: bool = False
    default: bool = False

    def protocol(self, name: str = "", key: str = "source.protocol") -> Protocol | None:
        """The protocol of that name (the first when empty); None for a kind without protocols."""
        if not self.protocols:
            if name:
                raise ConfigError(f"{key}: {name!r} is not allowed (allowed: none: source kind {self.name!r} has no "
                                  f"protocols)")
            return None
        if not name:
            return self.protocols[0]
        for p in self.protocols:
            if p.name == name:
                return p
        raise ConfigError(f"{key}: {name!r} is not allowed (allowed: "
                          f"{', '.join(repr(p.name) for p in self.protocols)})")

    def words(self, protocol: str = "") -> Words:
        """The counters of this kind with that protocol, and what is said about them."""
        p = self.protocol(protocol)
        counted = self.counters + (p.counters if p else ())
        return Words(counted, (p.no_decode if p and p.no_decode else None) or self.no_decode)

    def clock(self, protocol: str = "") -> bool:
        """Whether the samples' time is the unit's own clock (the configured rate is checked against it)."""
        p = self.protocol(protocol)
        return self.unit_clock if p is None or p.unit_clock is None else p.unit_clock

    def table_class(self) -> type:
        cls = resolve(self.config)
        if not (dataclasses.is_dataclass(cls) and issubclass(cls, SourceTable)):
            raise ConfigError(f"source kind {self.name!r}: its config {cls!r} is no dataclass deriving "
                              f"fluxcal.drivers.declare.SourceTable")
        if self.protocols and not issubclass(cls, ProtocolTable):
            raise ConfigError(f"source kind {self.name!r} has protocols: its config must derive ProtocolTable")
        return cls

    def load(self, table: Any, path: str = "source") -> Any:
        """Its [source] table read strictly (fluxcal.drivers.config.load_section), kind and protocol filled in."""
        obj = load_section(self.table_class(), table, path)
        obj.kind = self.name
        p = self.protocol(getattr(obj, "protocol", ""), f"{path}.protocol")
        if p is not None:
            obj.protocol = p.name
        return obj

    def open(self, configuration: Any) -> Any:
        """Its source, from the whole service configuration; a port that will not open is said with the keys to
        change first."""
        try:
            if self.opener is not None:
                return resolve(self.opener)(configuration)
            return resolve(self.factory)(configuration.source)
        except DriverError as e:
            if not self.port_keys:
                raise
            raise DriverError(f"{', '.join(self.port_keys)}: {e}") from None

    def open_table(self, table: dict, key: str, **options: Any) -> Any:
        """Its source from a [source] table built in code (a simulator's transport): only the keys its table has."""
        names = {f.name for f in dataclasses.fields(self.table_class())}
        try:
            config = self.load({k: v for k, v in table.items() if k in names})
        except ConfigError as e:
            raise ConfigError(f"{key}: cannot configure the {self.name} source behind it: {e}") from None
        return resolve(self.factory)(config, **options)


#: a declaration's code, as it may be given
Target = str | Callable[..., Any] | type
