"""The one contract every input implements: a Source yields SampleBlocks and keeps counters.

Serial, CAN, the simulated unit and MCAP replay are each one module implementing it, looked up
by name in SOURCES and imported only when used (like python-can's interface registry).
Subclasses implement `_read_block(timeout)`; `read` owns the timeout and the closed state.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass

from .block import SampleBlock
from .errors import ConfigError, DriverError


@dataclass
class Counters:
    """Health counters every source keeps; they only ever grow."""

    frames_accepted: int = 0
    crc_failures: int = 0       # serial: frames failing their CRC (CAN controllers drop those themselves)
    bad_frames: int = 0         # CAN: what the adapter could not make a frame of (a garbled SLCAN line)
    wrong_length: int = 0       # CAN: frames with the unit's ids that are no classic 8-byte data frame
    remote_frames: int = 0      # CAN: remote frames with the unit's ids (another node asking for them)
    error_frames: int = 0       # CAN: error frames the interface reports
    foreign_frames: int = 0     # CAN: frames of other nodes' (or reserved, or extended) ids, ignored: not a fault
    bytes_received: int = 0     # serial: every byte read from the port (fed to the framer)
    bytes_skipped: int = 0
    seq_gaps: int = 0           # number of gaps seen
    samples_missed: int = 0     # samples lost inside those gaps
    can_incomplete: int = 0     # CAN samples dropped because a frame never came
    duplicates: int = 0         # frames repeating one received before bit for bit (CAN: a frame already held), dropped
    seq_backsteps: int = 0      # frames whose counter or clock stepped back, no copy of one received (stale), dropped
    restarts: int = 0           # the unit restarted: counter and clock back near zero, followed on
    clock_jumps: int = 0        # the unit's clock jumped while its counter ran on: time repaired from the counter
    counter_jumps: int = 0      # the unit's counter jumped while its clock ran on: no sample counted missed
    saturated_axes: int = 0
    temp_invalid: int = 0
    implausible_samples: int = 0   # samples flagged implausible (FLAG_IMPLAUSIBLE): kept out of the estimator
    reserved_flags: int = 0        # ... of which: frames with flag bits the ICD says are 0
    beyond_full_scale: int = 0     # ... axes beyond the configured full scale (not at a rail)
    zero_vectors: int = 0          # ... probe vectors exactly (0, 0, 0)
    temp_out_of_range: int = 0     # ... probe temperatures outside the configured range (not flagged invalid)
    reconnects: int = 0
    read_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class Source(ABC):
    """A stream of SampleBlocks. `close()` may be called twice; usable as a context manager."""

    n_probes: int
    counters: Counters

    def __init__(self, n_probes: int) -> None:
        if not 1 <= n_probes <= 8:
            raise ConfigError(f"n_probes: {n_probes!r} is not allowed (allowed: 1..8)")
        self.n_probes = n_probes
        self.counters = Counters()
        self._closed = False

    def read(self, timeout: float | None = 0.1) -> SampleBlock | None:
        """The samples that arrived, or None if none came within `timeout` seconds.

        Raises DriverError when the port or bus failed (the caller may reconnect with `reopen`)."""
        if self._closed:
            raise DriverError(f"{type(self).__name__}: read after close")
        return self._read_block(timeout)

    @abstractmethod
    def _read_block(self, timeout: float | None) -> SampleBlock | None: ...

    def wait_readable(self, timeout: float) -> bool | None:
        """Wait up to `timeout` s for input without consuming it: True when some is there, False when
        none came, None when this source can only tell by reading (then call `read`). A reader that
        gathers a block of input first waits here, sleeps, and reads once: one parse per block."""
        return None

    def reopen(self) -> None:
        """Try to open the underlying port again after a DriverError; raise DriverError if it can't."""
        raise DriverError(f"{type(self).__name__} cannot reconnect")

    @property
    def exhausted(self) -> bool:
        """True for finite sources (files) once every sample has been read."""
        return False

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> "Source":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PortSource(Source):
    """A source on a port that fails and comes back (serial, CAN): subclasses `_open()` and `_drop()` the
    port, and name it in `port_label` for messages."""

    port_label = "port"

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _drop(self) -> None: ...

    def _before_reopen(self) -> None:
        """What a reconnect forgets besides the port (nothing by default)."""

    def reopen(self) -> None:
        if self._closed:
            raise DriverError(f"{self.port_label}: reopen after close")
        self._drop()
        self._before_reopen()
        self._open()

    def close(self) -> None:
        self._drop()
        super().close()


#: source kind -> "module:factory"; the factory takes (config, **kwargs) and returns a Source
SOURCES: dict[str, str] = {
    "serial": "fluxcal.drivers.serial_source:open_source",
    "can": "fluxcal.drivers.can_source:open_source",
    "sim": "fluxcal.drivers.sim.source:open_source",
    "replay": "fluxcal.drivers.mcap_source:open_source",
}


def open_source(kind: str, *args, **kwargs) -> Source:
    """Open a source by kind name, importing its module only now."""
    try:
        target = SOURCES[kind]
    except KeyError:
        raise ConfigError(f"source.kind: {kind!r} is not allowed (allowed: {', '.join(map(repr, SOURCES))})") from None
    module, _, factory = target.partition(":")
    return getattr(importlib.import_module(module), factory)(*args, **kwargs)
