"""The one contract every input implements: a Source yields SampleBlocks and keeps the counters its declaration
names.

Each kind of input is one module implementing it, declared once in drivers/kinds/ (fluxcal.drivers.declare.SourceKind),
looked up by name in fluxcal.drivers.registry and imported only when used (like python-can's interface registry).
Subclasses implement `_read_block(timeout)`; `read` owns the timeout and the closed state.
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod

from .block import SampleBlock
from .declare import Words, resolve
from .errors import ConfigError, DriverError


class Counters:
    """A source's health counters: the ones its declaration names (fluxcal.drivers.declare.Words, drivers/kinds/), each a
    whole number that only grows, with the words said about each (`words`). Made per declaration as a class with
    slots: adding to a counter costs what a plain attribute does, and one the declaration does not name is an
    AttributeError where it is counted, never a number nobody sees."""

    __slots__ = ()
    words: Words = Words(())

    def __init__(self) -> None:
        for name in self.words.names:
            setattr(self, name, 0)

    @staticmethod
    def of(words: Words) -> "Counters":
        """New counters, all 0, of the input `words` declares."""
        return _counters_class(words)()

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.words.names}

    def __repr__(self) -> str:
        return f"Counters({', '.join(f'{k}={v}' for k, v in self.as_dict().items())})"

    def __reduce__(self) -> tuple:
        return _rebuilt, (self.words, self.as_dict())


@functools.lru_cache(maxsize=None)
def _counters_class(words: Words) -> type[Counters]:
    return type("Counters", (Counters,), {"__slots__": words.names, "words": words})


def _rebuilt(words: Words, values: dict[str, int]) -> Counters:
    c = Counters.of(words)
    for k, v in values.items():
        setattr(c, k, v)
    return c


class Source(ABC):
    """A stream of SampleBlocks. `close()` may be called twice; usable as a context manager."""

    n_probes: int
    counters: Counters

    def __init__(self, n_probes: int, counters: Counters | None = None) -> None:
        """counters: the ones the source's declaration names (SourceKind.words); none by default."""
        if not 1 <= n_probes <= 8:
            raise ConfigError(f"n_probes: {n_probes!r} is not allowed (allowed: 1..8)")
        self.n_probes = n_probes
        self.counters = counters if counters is not None else Counters.of(Words(()))
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

    def drain(self) -> SampleBlock | None:
        """At the end of reading (the service stops): what the source still holds that no more input will complete,
        released as it is, and what cannot be released counted; None when it holds nothing (the default)."""
        return None

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


def open_source(kind: str, *args, **kwargs) -> Source:
    """Open a source by kind name (fluxcal.drivers.registry), importing its module only now: the kind's factory with these
    arguments (its [source] table, or the keywords it takes)."""
    from .registry import source_kind

    return resolve(source_kind(kind).factory)(*args, **kwargs)
