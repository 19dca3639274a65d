"""The serial source: ICD frames from a serial port (RS-422 / USB-serial, a pty, any pyserial URL).

    [source]
    kind = "serial"
    protocol = "icd"             # how bytes become samples (drivers/kinds/serial.py declares the protocols)
    port = "/dev/ttyUSB0"        # or a pyserial URL: "socket://host:port", "rfc2217://...", "loop://"
    baudrate = 921600
    n_probes = 2                 # must equal unit.n_probes
    lsb_nT = 0.001               # nT per ADC count
    read_timeout_s = 0.02        # longest single wait on the port
    rate_hz = 200.0              # the unit's sample rate (the service counts its durations in samples at it)
    full_scale_nT = 1000000.0    # plausibility: a larger |axis| (not at a rail) flags the sample implausible
    temp_min_C = -100.0          # ... and so does a probe temperature outside [temp_min_C, temp_max_C]
    temp_max_C = 200.0

A pulled cable (or a closed pty) makes `read` raise DriverError; `reopen()` opens the same port
again (a udev symlink that reappears works). The caller counts read_errors and reconnects.

A protocol's decoder takes the bytes as they come: `feed(data, rx_time_s)` gives the SampleBlock of the frames
they complete (None when none), `discard_tail()` forgets a partial frame when the port is reopened; it counts
into the counters it is given (SerialIcd: the ICD's frames).
"""

from __future__ import annotations

import fcntl
import os
import select
import time
from dataclasses import dataclass

import serial

from .assemble import FrameAssembler, SerialFramer, serial_icd_counters
from .plausibility import Plausibility, check_temp_range, plausibility_spec
from .block import SampleBlock
from .config import spec
from .declare import ProtocolTable, resolve
from .errors import ConfigError, DriverError
from .icd import DEFAULT_LSB_NT, MAX_PROBES
from .kinds.serial import KIND
from .registry import source_kind
from .source import Counters, PortSource

#: most bytes taken from the port per read call (about 11 s of data at 921600 baud)
MAX_READ_BYTES = 1 << 20
#: bytes asked of a non-blocking port in its first read (a block of 8 ms at 921600 baud is about 740; below malloc's
#: mmap threshold, so the buffer is no system call of its own)
DIRECT_READ_BYTES = 1 << 16


@dataclass(kw_only=True)
class SerialConfig(ProtocolTable):
    """The [source] table of the serial kind (keyword-only: required keys need no order)."""

    port: str = spec(doc="device path (/dev/ttyUSB0, /dev/pts/N) or pyserial URL (socket://host:port)")
    baudrate: int = spec(921600, min=1, max=100_000_000)
    n_probes: int = spec(min=1, max=MAX_PROBES, doc="probes per frame; must equal unit.n_probes")
    lsb_nT: float = spec(DEFAULT_LSB_NT, min=1e-9, max=1e3, doc="nT per ADC count")
    read_timeout_s: float = spec(0.02, min=0.001, max=5.0, doc="longest single wait on the port, s")
    rate_hz: float | None = spec(None, min=0.001, max=100_000.0,
                                 doc="the unit's sample rate, Hz: the service counts its durations (estimator "
                                     "window_s, check_every_s, update_every_s) in samples at this rate; the "
                                     "driver itself takes time from the unit clock in each frame")
    full_scale_nT: float = plausibility_spec()["full_scale_nT"]
    temp_min_C: float = plausibility_spec()["temp_min_C"]
    temp_max_C: float = plausibility_spec()["temp_max_C"]

    def validate(self, path: str) -> None:
        check_temp_range(self.temp_min_C, self.temp_max_C, path or "source")


class SerialIcd:
    """The serial kind's ICD protocol (drivers/kinds/serial.py): bytes as they come -> SampleBlocks, the tail of a
    frame kept for the next bytes (SerialFramer, then FrameAssembler)."""

    def __init__(self, n_probes: int, *, lsb_nT: float, counters: Counters | None = None,
                 plausibility: Plausibility | None = Plausibility()) -> None:
        self.counters = counters if counters is not None else serial_icd_counters()
        self.framer = SerialFramer(n_probes, self.counters)
        self.assembler = FrameAssembler(n_probes, lsb_nT, self.counters, plausibility=plausibility)

    def feed(self, data: bytes, rx_time_s: float | None = None) -> SampleBlock | None:
        """The samples of the frames `data` completes (None when it completes none)."""
        frames = self.framer.feed(data)
        return self.assembler.block(frames, rx_time_s=rx_time_s) if len(frames) else None

    def discard_tail(self) -> None:
        self.framer.discard_tail()


class SerialSource(PortSource):
    """SampleBlocks from a unit's frames on a serial port, by its protocol (the ICD's by default).

    Reads what is available (waiting at most `read_timeout_s` at a time, never forever) and counts it
    (bytes_received); the protocol's decoder keeps the unconsumed tail of a frame for the next read and counts
    what it finds (frames accepted, CRC failures, bytes skipped, ...) in `counters`.
    """

    def __init__(self, port: str, *, n_probes: int, baudrate: int = 921600, lsb_nT: float = DEFAULT_LSB_NT,
                 read_timeout_s: float = 0.02, plausibility: Plausibility | None = Plausibility(),
                 protocol: str = "") -> None:
        kind = source_kind(KIND.name)              # as registered: with the protocols added to it
        proto = kind.protocol(protocol)
        super().__init__(n_probes, Counters.of(kind.words(proto.name)))
        if not read_timeout_s > 0:
            # timeout=0 spins and None blocks forever (DEPENDENCIES.md)
            raise ConfigError(f"source.read_timeout_s: {read_timeout_s!r} is not allowed (allowed: > 0)")
        if not lsb_nT > 0:
            raise ConfigError(f"source.lsb_nT: {lsb_nT!r} is not allowed (allowed: > 0)")
        self.port = port
        self.port_label = f"serial port {port}"
        self.baudrate = int(baudrate)
        self.lsb_nT = float(lsb_nT)
        self.read_timeout_s = float(read_timeout_s)
        self.protocol = proto.name
        self._decoder = resolve(proto.decoder)(n_probes, lsb_nT=self.lsb_nT, counters=self.counters,
                                               plausibility=plausibility)
        self._ser: serial.SerialBase | None = None
        self._fd: int | None = None       # a native port's descriptor when it is non-blocking (pyserial's own)
        self._open()

    def _open(self) -> None:
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=self.read_timeout_s)
        except (serial.SerialException, OSError, ValueError) as e:
            self._ser = None
            raise DriverError(f"serial port {self.port}: cannot open ({e}); check the device path or URL, "
                              f"that the adapter is plugged in and that no other program holds it") from e
        fd = getattr(self._ser, "fd", None)
        try:
            self._fd = fd if isinstance(fd, int) and fd >= 0 and fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_NONBLOCK \
                else None
        except OSError:
            self._fd = None

    def _fail(self, e: BaseException) -> DriverError:
        self._drop()
        return DriverError(f"serial port {self.port}: read failed ({e}): the cable or adapter was probably "
                           f"disconnected")

    def _drop(self) -> None:
        ser, self._ser, self._fd = self._ser, None, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass   # the port is already gone; closing it is only tidying up

    def _pull(self, wait: bool) -> bytes:
        """What the port has now; with `wait`, first wait up to read_timeout_s for a byte."""
        ser = self._ser
        if ser is None:
            raise DriverError(f"serial port {self.port}: not open (a previous read failed; reopen() opens it again)")
        try:
            if self._fd is not None:
                # a non-blocking native port: one read(2) takes what is there, without asking first (an ioctl less)
                try:
                    now = os.read(self._fd, DIRECT_READ_BYTES)
                except BlockingIOError:
                    now = b""
                if len(now) == DIRECT_READ_BYTES:            # more may wait: the rest as below
                    return now + self._drain(ser, ser.in_waiting)
                if now:
                    return now
                # nothing there (a tty may say so with 0 bytes, as a port whose other end went away does): ask as below
            data = b""
            waiting = ser.in_waiting
            if waiting == 0:
                if not wait:
                    return b""
                # read(1): returns at the first byte or after read_timeout_s. Never a larger blocking
                # read: pyserial drops what it has collected when the port fails mid-read.
                data = ser.read(1)
                if not data:
                    return b""
                waiting = ser.in_waiting
            return data + self._drain(ser, waiting)
        except (serial.SerialException, OSError) as e:
            raise self._fail(e) from e

    @staticmethod
    def _drain(ser: serial.SerialBase, waiting: int) -> bytes:
        """Whatever the port holds now (`waiting`, its in_waiting just read), without waiting."""
        if waiting == 0:
            return b""
        fd = getattr(ser, "fd", None)
        if isinstance(fd, int) and fd >= 0:
            # a native port: one read(2) of what is there. pyserial's read() loops, and when the port
            # fails within the loop it throws away what it had collected; one system call either
            # returns the bytes or fails having taken none, so nothing read is ever lost uncounted
            data = os.read(fd, min(waiting, MAX_READ_BYTES))
            if not data:                 # readable yet empty: the other end is gone (as pyserial says it)
                raise serial.SerialException("device reports readiness to read but returned no data "
                                             "(device disconnected or multiple access on port?)")
            return data
        if waiting > 1:
            return ser.read(min(waiting, MAX_READ_BYTES))
        # in_waiting is only a readiness flag (0/1) on some URL handlers (socket://): read what is
        # there with a zero timeout rather than byte by byte
        saved = ser.timeout
        ser.timeout = 0
        try:
            return ser.read(MAX_READ_BYTES)
        finally:
            ser.timeout = saved

    def wait_readable(self, timeout: float) -> bool | None:
        ser = self._ser
        if ser is None:
            raise DriverError(f"serial port {self.port}: not open (a previous read failed; reopen() opens it again)")
        fileno = getattr(ser, "fileno", None)
        if fileno is None:
            return None                   # URL handlers (socket://, loop://): tell by reading
        try:
            # a port whose other end went away is readable too: the read that follows raises
            return bool(select.select([fileno()], [], [], max(timeout, 0.0))[0])
        except (serial.SerialException, OSError, ValueError) as e:
            raise self._fail(e) from e

    def _read_block(self, timeout: float | None) -> SampleBlock | None:
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        while True:
            remaining = None if deadline is None else deadline - time.monotonic()
            data = self._pull(wait=remaining is None or remaining > 0)
            if data:
                self.counters.bytes_received += len(data)
                block = self._decoder.feed(data, rx_time_s=time.monotonic())
                if block is not None:
                    return block
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def _before_reopen(self) -> None:
        """A partial frame from before is dropped (counted as skipped). Unwrapping continues, so samples
        lost meanwhile show up as a seq gap."""
        self._decoder.discard_tail()

    def __repr__(self) -> str:
        return (f"SerialSource({self.port!r}, n_probes={self.n_probes}, baudrate={self.baudrate}, "
                f"protocol={self.protocol!r})")


def open_source(config: SerialConfig | None = None, **kwargs) -> SerialSource:
    """The serial kind's factory (drivers/kinds/serial.py): from a SerialConfig, keyword arguments
    (port, baudrate, n_probes, lsb_nT, read_timeout_s, protocol), or a config with keyword overrides. A config's
    rate_hz is the service's business (the driver takes time from the unit clock in each frame); as a
    keyword it is accepted and not used."""
    kwargs.pop("rate_hz", None)
    if config is None:
        if "port" not in kwargs or "n_probes" not in kwargs:
            raise ConfigError("source: a serial source needs port and n_probes")
        kwargs.pop("kind", None)
        return SerialSource(kwargs.pop("port"), **kwargs)
    values = {k: getattr(config, k) for k in ("port", "baudrate", "n_probes", "lsb_nT", "read_timeout_s", "protocol")}
    unknown = set(kwargs) - set(values) - {"plausibility"}
    if unknown:
        raise ConfigError(f"source: unknown serial option(s) {', '.join(sorted(unknown))} "
                          f"(allowed: {', '.join(values)})")
    values["plausibility"] = Plausibility(config.full_scale_nT, config.temp_min_C, config.temp_max_C)
    values.update(kwargs)
    return SerialSource(values.pop("port"), **values)
