"""The CAN source: ICD CAN frames (one frame per probe axis per sample) from a python-can bus, and
CAN log files (candump .log, .asc, .blf, .csv) assembled the same way for `fluxcal decode`.

    [source]
    kind = "can"
    protocol = "icd"             # how frames become samples (drivers/kinds/can.py declares the protocols)
    interface = "socketcan"      # any python-can interface: "virtual" (tests), "slcan" (USB-CAN on a tty)
    channel = "can0"             # "vcan0", "/dev/ttyACM0" for slcan, any name for virtual
    bitrate = 1000000
    base_id = 0x200              # 512
    n_probes = 2                 # must equal unit.n_probes
    lsb_nT = 0.001
    rate_hz = 500.0              # the unit's sample rate: CAN carries no unit clock, t_s = seq / rate_hz
    window_samples = 32          # an incomplete sample is dropped once seq moved on by more than this
    window_s = 0.5               # ... or once this long has passed since its first frame
    full_scale_nT = 1000000.0    # plausibility, as for serial (drivers/plausibility.py)
    temp_min_C = -100.0
    temp_max_C = 200.0

CAN carries no timestamp from the unit, only the uint16 seq; t_s is therefore the unwrapped seq
divided by the configured rate_hz (sample instants on the unit's own clock, not the host's).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np

from .assemble import CanAssembler, CanSamples, SeqGapCounter
from .block import SampleBlock
from .config import spec
from .declare import ProtocolTable, resolve
from .errors import ConfigError, DataError, DriverError
from .icd import DEFAULT_CAN_BASE_ID, DEFAULT_LSB_NT, MAX_PROBES
from .kinds.can import KIND
from .plausibility import Plausibility, check_temp_range, plausibility_spec
from .registry import source_kind
from .source import Counters, PortSource

MAX_STANDARD_ID = 0x7FF
#: suffixes python-can's LogReader reads that keep everything an ICD frame needs
CAN_LOG_SUFFIXES = (".log", ".asc", ".blf", ".csv")


@dataclass(kw_only=True)
class CanConfig(ProtocolTable):
    """The [source] table of the CAN kind (keyword-only: required keys need no order)."""

    interface: str = spec("socketcan", doc="python-can interface name: socketcan, slcan, virtual, ...")
    channel: str = spec(doc="can0, /dev/ttyACM0 (slcan), or a virtual channel name")
    bitrate: int = spec(1_000_000, min=10_000, max=1_000_000)
    base_id: int = spec(DEFAULT_CAN_BASE_ID, min=0, max=MAX_STANDARD_ID,
                        doc="id of probe 1 x; probe k axis a is base_id + 4k + a")
    n_probes: int = spec(min=1, max=MAX_PROBES, doc="must equal unit.n_probes")
    lsb_nT: float = spec(DEFAULT_LSB_NT, min=1e-9, max=1e3, doc="nT per ADC count")
    rate_hz: float = spec(min=0.001, max=100_000.0,
                          doc="the unit's sample rate; CAN has no unit clock, so t_s = seq / rate_hz")
    window_samples: int = spec(32, min=1, max=65536 // 8,
                               doc="drop an incomplete sample once seq moved on by more than this")
    window_s: float = spec(0.5, min=0.001, max=60.0, doc="drop an incomplete sample this long after its first frame")
    max_batch: int = spec(4096, min=1, max=1 << 20, doc="most frames assembled per read")
    full_scale_nT: float = plausibility_spec()["full_scale_nT"]
    temp_min_C: float = plausibility_spec()["temp_min_C"]
    temp_max_C: float = plausibility_spec()["temp_max_C"]

    def validate(self, path: str) -> None:
        check_base_id(self.base_id, self.n_probes, f"{path}.base_id" if path else "base_id")
        check_temp_range(self.temp_min_C, self.temp_max_C, path or "source")


def check_base_id(base_id: int, n_probes: int, key: str = "base_id") -> None:
    """The unit's ids base .. base + 4n - 1 must fit the 11-bit standard id space."""
    top = base_id + 4 * n_probes - 1
    if base_id < 0 or top > MAX_STANDARD_ID:
        raise ConfigError(f"{key}: {base_id:#x} is not allowed for {n_probes} probes (allowed: 0 .. "
                          f"{MAX_STANDARD_ID - 4 * n_probes + 1:#x}, ids up to base + 4n - 1 must fit 11 bits)")


@dataclass
class FrameKinds:
    """How many frames of a batch were of each kind besides the ICD frames kept (Counters of the same names)."""

    foreign_frames: int = 0       # other nodes' ids or an extended (29-bit) id: the bus is shared, not a fault
    wrong_length: int = 0         # the unit's ids, but not a classic 8-byte data frame (another length, CAN FD)
    remote_frames: int = 0        # the unit's ids as remote frames (another node asking for them)
    error_frames: int = 0         # error frames the interface reports (a fault on the bus itself)

    def add_to(self, counters: Counters) -> None:
        for key, value in vars(self).items():
            setattr(counters, key, getattr(counters, key) + value)


def _frames_from_messages(msgs: list[can.Message], lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                              FrameKinds]:
    """(ids, payloads (M, 8), timestamps) of the ICD-shaped frames, and how many frames were of each other kind
    (FrameKinds): every frame is one or the other."""
    ids, data, stamps = [], [], []
    kinds = FrameKinds()
    for m in msgs:
        if m.is_error_frame:
            kinds.error_frames += 1
        elif m.is_extended_id or not lo <= m.arbitration_id <= hi:
            kinds.foreign_frames += 1
        elif m.is_remote_frame:
            kinds.remote_frames += 1
        elif m.dlc != 8 or m.is_fd or len(m.data) != 8:
            kinds.wrong_length += 1
        else:
            ids.append(m.arbitration_id)
            data.append(bytes(m.data))
            stamps.append(m.timestamp)
    payloads = np.frombuffer(b"".join(data), dtype=np.uint8).reshape(-1, 8)
    return np.asarray(ids, dtype=np.int64), payloads, np.asarray(stamps, dtype=np.float64), kinds


class CanIcd:
    """The CAN kind's ICD protocol (drivers/kinds/can.py): a batch of python-can messages -> the SampleBlock of the
    samples it completes. Every message is counted once, by kind (FrameKinds, and frames_accepted); the samples
    assembled (CanAssembler) are counted for gaps and scaled with t_s = seq / rate_hz (CAN has no unit clock)."""

    def __init__(self, n_probes: int, *, rate_hz: float, lsb_nT: float, counters: Counters,
                 base_id: int = DEFAULT_CAN_BASE_ID, window_samples: int = 32, window_s: float = 0.5,
                 plausibility: Plausibility | None = Plausibility()) -> None:
        self.rate_hz, self.lsb_nT, self.counters, self.plausibility = rate_hz, lsb_nT, counters, plausibility
        self._assembler = CanAssembler(n_probes, base_id=base_id, window_samples=window_samples,
                                       window_s=window_s, counters=counters, rate_hz=rate_hz)
        self._gaps = SeqGapCounter()
        self._id_range = (base_id, base_id + 4 * n_probes - 1)

    def decode(self, msgs: list[can.Message], now_s: float) -> SampleBlock | None:
        ids, payloads, _, kinds = _frames_from_messages(msgs, *self._id_range)
        kinds.add_to(self.counters)
        samples = self._assembler.push(ids, payloads, now_s, now_s=now_s)
        if not len(samples):
            return None
        return self._block(samples)

    def finish(self) -> SampleBlock | None:
        """The end of input: every sample the assembler holds, the complete ones released (those waiting behind an
        incomplete one too) and the incomplete ones counted (can_incomplete); None when it held none complete."""
        samples = self._assembler.flush()
        return self._block(samples) if len(samples) else None

    def _block(self, samples: CanSamples) -> SampleBlock:
        self._gaps.update(samples.seq, self.counters)
        return samples.to_block(rate_hz=self.rate_hz, lsb_nT=self.lsb_nT, counters=self.counters,
                                plausibility=self.plausibility)


class CanSource(PortSource):
    """SampleBlocks from a unit's frames on a python-can bus, by its protocol (the ICD's by default).

    Each read drains what the bus holds (bounded receive: `bus.recv` with a timeout, then without
    waiting, at most `max_batch` frames) and hands the batch to the protocol's decoder (`decode(messages, now_s)`,
    CanIcd: assembled with numpy, fluxcal.drivers.assemble.CanAssembler). Every frame received is counted once, by kind:
    frames_accepted (the unit's ICD frames), foreign_frames (other nodes' ids), wrong_length, remote_frames and
    error_frames (FrameKinds), and bad_frames: what the adapter could not make a frame of (a garbled SLCAN line,
    fluxcal.drivers.slcan; an exception of any other interface's parser), never the service's end. The controller itself
    drops frames with a bad CRC, so CAN has no CRC failures. Then can_incomplete, seq_gaps, samples_missed,
    saturated_axes as the assembler finds them.
    """

    def __init__(self, *, interface: str, channel: str, n_probes: int, rate_hz: float,
                 bitrate: int = 1_000_000, base_id: int = DEFAULT_CAN_BASE_ID, lsb_nT: float = DEFAULT_LSB_NT,
                 window_samples: int = 32, window_s: float = 0.5, max_batch: int = 4096,
                 bus_kwargs: dict | None = None, plausibility: Plausibility | None = Plausibility(),
                 protocol: str = "") -> None:
        kind = source_kind(KIND.name)              # as registered: with the protocols added to it
        proto = kind.protocol(protocol)
        super().__init__(n_probes, Counters.of(kind.words(proto.name)))
        check_base_id(base_id, n_probes, "source.base_id")
        if not rate_hz > 0:
            raise ConfigError(f"source.rate_hz: {rate_hz!r} is not allowed (allowed: > 0; CAN carries no unit "
                              f"clock, so the sample rate sets t_s = seq / rate_hz)")
        if not lsb_nT > 0:
            raise ConfigError(f"source.lsb_nT: {lsb_nT!r} is not allowed (allowed: > 0)")
        self.interface, self.channel, self.bitrate = interface, channel, int(bitrate)
        self.port_label = f"CAN bus {interface}:{channel}"   # reopen() keeps partial samples: their frames may still come
        self.base_id, self.rate_hz, self.lsb_nT = int(base_id), float(rate_hz), float(lsb_nT)
        self.max_batch = int(max_batch)
        self._bus_kwargs = dict(bus_kwargs or {})
        self.protocol = proto.name
        self._decoder = resolve(proto.decoder)(n_probes, rate_hz=self.rate_hz, lsb_nT=self.lsb_nT,
                                               counters=self.counters, base_id=self.base_id,
                                               window_samples=window_samples, window_s=window_s,
                                               plausibility=plausibility)
        for method in ("decode", "finish"):           # the CAN kind's decoder interface (declare.Protocol)
            if not callable(getattr(self._decoder, method, None)):
                raise ConfigError(f"source.protocol: {proto.name!r}: its decoder has no {method}() (a CAN protocol's "
                                  f"decoder takes decode(messages, now_s) and gives what it holds at the stop with "
                                  f"finish(): docs/sources.md)")
        self._bus: can.BusABC | None = None
        self._bad_lines_seen = 0
        self._open()

    def _open(self) -> None:
        try:
            if self.interface == "slcan":          # python-can's slcan with a parser that never raises
                from .slcan import SlcanBus

                self._bus = SlcanBus(channel=self.channel, bitrate=self.bitrate, **self._bus_kwargs)
            else:
                self._bus = can.Bus(interface=self.interface, channel=self.channel, bitrate=self.bitrate,
                                    **self._bus_kwargs)
            self._bad_lines_seen = 0
        except (can.CanError, OSError, ValueError, ImportError) as e:
            self._bus = None
            raise DriverError(f"CAN bus {self.interface}:{self.channel}: cannot open ({e}); check the interface "
                              f"name, the channel and that the adapter is plugged in") from e

    def _drop(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except (can.CanError, OSError, ValueError):
                pass   # the adapter is already gone; shutting down is only tidying up

    def _receive(self, wait_s: float | None) -> list[can.Message]:
        bus = self._bus
        if bus is None:
            raise DriverError(f"CAN bus {self.interface}:{self.channel}: not open (a previous read failed; reopen() "
                              f"opens it again)")
        batch: list[can.Message] = []
        try:
            wait: float | None = wait_s
            for _ in range(self.max_batch):   # frames, or garbled ones: a parser that always raises ends here too
                try:
                    msg = bus.recv(timeout=wait)
                except (can.CanError, OSError):
                    raise
                except Exception:  # noqa: BLE001 - an interface's parser that raises on a garbled frame
                    self.counters.bad_frames += 1
                    wait = 0.0                      # the frames after it may be there already
                    continue
                if msg is None:
                    break
                batch.append(msg)
                wait = 0.0
        except (can.CanError, OSError) as e:
            # OSError covers pyserial's SerialException, which serial-based interfaces may let through
            self._drop()
            raise DriverError(f"CAN bus {self.interface}:{self.channel}: receive failed ({e}): the adapter was "
                              f"probably disconnected") from e
        finally:
            bad = getattr(bus, "bad_lines", 0)              # fluxcal.drivers.slcan counts the lines that are no frame
            self.counters.bad_frames += bad - self._bad_lines_seen
            self._bad_lines_seen = bad
        return batch

    def _read_block(self, timeout: float | None) -> SampleBlock | None:
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        while True:
            remaining = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            # wait in short steps when blocking, so incomplete samples still expire on a silent bus
            wait = min(remaining, 0.1) if remaining is not None else 0.1
            block = self._decoder.decode(self._receive(wait), time.monotonic())
            if block is not None:
                return block
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def drain(self) -> SampleBlock | None:
        """At the service's stop: the frames the bus still holds, then every sample the assembler holds (complete
        ones released, those behind an incomplete one too; incomplete ones counted). Held samples were lost
        uncounted at a stop, and when the adapter had gone away before it (30 of 3,386 in a field trial)."""
        parts = []
        if self._bus is not None:
            try:
                block = self._decoder.decode(self._receive(0.0), time.monotonic())
            except DriverError:
                block = None                        # the adapter is gone: what it held is gone with it
            if block is not None:
                parts.append(block)
        last = self._decoder.finish()
        if last is not None:
            parts.append(last)
        return None if not parts else parts[0] if len(parts) == 1 else SampleBlock.concat(parts)

    def __repr__(self) -> str:
        return (f"CanSource({self.interface!r}, {self.channel!r}, n_probes={self.n_probes}, base_id={self.base_id:#x}, "
                f"protocol={self.protocol!r})")


def open_source(config: CanConfig | None = None, **kwargs) -> CanSource:
    """The CAN kind's factory (drivers/kinds/can.py): from a CanConfig, keyword arguments
    (interface, channel, n_probes, rate_hz, bitrate, base_id, lsb_nT, window_samples, window_s,
    max_batch, bus_kwargs, protocol), or a config with keyword overrides."""
    if config is None:
        kwargs.pop("kind", None)
        missing = [k for k in ("interface", "channel", "n_probes", "rate_hz") if k not in kwargs]
        if missing:
            raise ConfigError(f"source: a CAN source needs {', '.join(missing)}")
        return CanSource(**kwargs)
    names = ("interface", "channel", "n_probes", "rate_hz", "bitrate", "base_id", "lsb_nT", "window_samples",
             "window_s", "max_batch", "protocol")
    values = {k: getattr(config, k) for k in names}
    unknown = set(kwargs) - set(values) - {"bus_kwargs", "plausibility"}
    if unknown:
        raise ConfigError(f"source: unknown CAN option(s) {', '.join(sorted(unknown))} (allowed: {', '.join(names)})")
    values["plausibility"] = Plausibility(config.full_scale_nT, config.temp_min_C, config.temp_max_C)
    values.update(kwargs)
    return CanSource(**values)


def read_can_log(path: str | Path, n_probes: int, *, base_id: int = DEFAULT_CAN_BASE_ID,
                 window_samples: int = 32, window_s: float = 0.5, counters: Counters | None = None,
                 chunk_frames: int = 65536) -> tuple[CanSamples, Counters]:
    """Assemble the samples in a CAN log (python-can's LogReader picks the format by suffix:
    candump .log, .asc, .blf, .csv) exactly as the live source does, using the log's timestamps
    for the time limit. Returns the complete samples (seq unwrapped) and the counters.

    Raises DataError naming the file when it cannot be read."""
    p = Path(path)
    counters = counters if counters is not None else Counters.of(KIND.words())
    check_base_id(base_id, n_probes, "--base-id")
    suffix = p.suffix.lower()
    if suffix not in CAN_LOG_SUFFIXES:
        raise DataError(f"{p}: unknown CAN log format {p.suffix!r} (allowed: {', '.join(CAN_LOG_SUFFIXES)})")
    assembler = CanAssembler(n_probes, base_id=base_id, window_samples=window_samples, window_s=window_s,
                             counters=counters)
    id_range = (base_id, base_id + 4 * n_probes - 1)
    parts: list[CanSamples] = []
    try:
        reader = can.LogReader(p)
    except FileNotFoundError:
        raise DataError(f"{p}: CAN log not found") from None
    except (OSError, ValueError) as e:
        raise DataError(f"{p}: cannot read as a CAN log ({e})") from e
    try:
        with reader:
            batch: list[can.Message] = []
            for msg in reader:
                batch.append(msg)
                if len(batch) >= chunk_frames:
                    parts.append(_push_log_batch(assembler, batch, id_range, counters))
                    batch = []
            parts.append(_push_log_batch(assembler, batch, id_range, counters))
    except (ValueError, IndexError, KeyError, OSError, EOFError, can.CanError) as e:
        raise DataError(f"{p}: not a readable {suffix} CAN log ({type(e).__name__}: {e})") from e
    parts.append(assembler.flush())
    return CanSamples.concat(parts, n_probes), counters


def _push_log_batch(assembler: CanAssembler, batch: list[can.Message], id_range: tuple[int, int],
                    counters: Counters) -> CanSamples:
    ids, payloads, stamps, kinds = _frames_from_messages(batch, *id_range)
    kinds.add_to(counters)
    return assembler.push(ids, payloads, stamps)


def estimate_rate_hz(samples: CanSamples) -> float | None:
    """The unit's sample rate from the receive timestamps of a CAN log.

    Least-squares line through (seq, rx_time): rate = 1 / slope, rounded to a power of ten between
    10 and 100 times its standard error (so the estimate's own error, a few sigma, rounds away), so
    a 500 Hz unit logged with jittery host timestamps gives exactly 500 rather than 500.0013. None when the log cannot tell (fewer than two samples, or
    timestamps that do not advance).
    """
    if len(samples) < 2 or np.ptp(samples.seq) == 0:
        return None
    x = (samples.seq - samples.seq[0]).astype(np.float64)
    y = samples.rx_time_s - samples.rx_time_s[0]
    if len(samples) >= 4:
        (slope, _), cov = np.polyfit(x, y, 1, cov=True)
        sigma_slope = float(np.sqrt(max(cov[0, 0], 0.0)))
    else:
        slope, _ = np.polyfit(x, y, 1)
        sigma_slope = 0.0
    if not np.isfinite(slope) or slope <= 0:
        return None
    rate = 1.0 / slope
    sigma_rate = sigma_slope / slope**2                    # d(1/s) = ds / s^2
    decimals = 9 if sigma_rate <= 0 else int(np.clip(np.floor(-np.log10(10 * sigma_rate)), -6, 9))
    rounded = round(rate, decimals)
    return float(rounded) if rounded > 0 else float(rate)
