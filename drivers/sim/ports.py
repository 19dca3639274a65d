"""Emitters that put the simulated unit on a port, in a background thread, like the hardware would:

- PtyEmitter: ICD serial bytes on a pseudo-terminal that pyserial opens like /dev/ttyUSB0;
- CanEmitter: ICD CAN frames on a python-can bus (interface "virtual" links buses in one process);
- SlcanEmitter: an SLCAN (Lawicel) USB-CAN adapter on a pty, for python-can's `slcan` interface,
  so CAN crosses processes on machines without vcan.

Every emitter streams samples [start_index, n_samples) of a Unit, paced by the wall clock
(realtime) or as fast as the reader takes them, and stops by itself at the end of the run, on
close(), or with the interpreter (daemon thread). Faults are the Unit's; the emitter adds outages
(faults.outage_at_s / outage_s: the port closes) and silences (faults.silence_at_s / silence_s: nothing
sent, the port open) and keeps the FaultRecord of everything it did.

The pty and reconnection. A pty slave (/dev/pts/N) disappears when its master closes and cannot
be opened again, so an emitter never hands out the slave path itself: `emitter.path` is a symlink
in a private temporary directory that points at the current /dev/pts/N. An outage waits until the
reader has read what was sent (and close_grace_s more: pyserial discards the bytes a blocked
read(size) has collected when the port fails, so readers should read `in_waiting` bytes), closes the
master (the reader's next read fails: pyserial raises SerialException), and removes the symlink
(reopening fails with FileNotFoundError, like an unplugged adapter); after outage_s it opens a new pty
and points the symlink at it, so a reader configured with `emitter.path` reconnects by opening the
same path again. Samples of the outage are never sent and are recorded as `outage`.

Nobody listening. pyserial flushes the input queue when it opens a port, and a real unit's UART
sends whether or not anyone listens. So while no reader has the slave open (POLLHUP on the master),
a realtime emitter throws the samples away and records them as `no_reader`; a fast emitter waits for
a reader, then `settle_s` more (so the reader's open-time flush cannot eat the first frames).
SLCAN additionally forwards frames only between the host's 'O' (open) and 'C' (close) commands."""

from __future__ import annotations

import errno
import fcntl
import os
import select
import shutil
import struct
import tempfile
import termios
import threading
import time
import tty
from typing import Any

from ..errors import DriverError
from .unit import FaultRecord, Unit


class Emitter:
    """Base of the emitters: the pacing loop, outages, the thread. Subclasses provide the port."""

    label = "emitter"                    # in its thread's name and its errors

    def __init__(self, unit: Unit, *, realtime: bool | None = None, block_s: float = 0.02, start_index: int = 0,
                 record: FaultRecord | None = None, settle_s: float = 0.05, drain_timeout_s: float = 5.0,
                 close_grace_s: float = 0.25, close_at_end: bool = False) -> None:
        self.unit = unit
        self.realtime = unit.config.realtime if realtime is None else bool(realtime)
        self.block_n = max(1, int(round(block_s * unit.rate_hz)))
        self.start_index = start_index
        self.record = record if record is not None else FaultRecord()
        self.settle_s = settle_s
        self.drain_timeout_s = drain_timeout_s
        self.close_grace_s = close_grace_s
        self.close_at_end = close_at_end
        self.next_index = start_index        # first sample not yet handled
        self.reconnects = 0                  # outages survived
        self.error: BaseException | None = None
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._present_since: float | None = None

    # -- port hooks (subclasses) ------------------------------------------------------------------------
    def _open_port(self) -> None: ...

    def _close_port(self) -> None: ...

    def _reader_present(self) -> bool:
        return True

    def _service(self) -> None:
        """Called often from the thread: answer the host (SLCAN commands)."""

    def _send(self, start: int, stop: int) -> bool:
        """Send samples [start, stop); False if the reader went away meanwhile."""
        raise NotImplementedError

    def _drain(self, timeout_s: float) -> None:
        """Wait until the reader has taken what was sent (bounded)."""

    # -- lifecycle ----------------------------------------------------------------------------------------
    def start(self) -> "Emitter":
        """Open the port and start streaming in a daemon thread; returns self."""
        if self._thread is not None:
            raise RuntimeError("emitter already started")
        self._open_port()
        self._thread = threading.Thread(target=self._run, name=f"fluxcal-sim-{self.label}", daemon=True)
        self._thread.start()
        return self

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the run is over; True if it is. Raises the thread's error, if it had one."""
        finished = self.done.wait(timeout)
        if self.error is not None:
            raise DriverError(f"simulated {self.label} emitter failed: {self.error}") from self.error
        return finished

    def close(self) -> None:
        """Stop the thread and close the port; safe to call twice."""
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5.0)
        with self._lock:
            self._close_port()

    def __enter__(self) -> "Emitter":
        return self.start() if self._thread is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the loop -----------------------------------------------------------------------------------------
    def _sleep_until(self, deadline: float) -> bool:
        """Serve the host until the monotonic deadline; False if stopped."""
        while not self._stop.is_set():
            self._service()
            left = deadline - time.monotonic()
            if left <= 0:
                return True
            self._stop.wait(min(left, 0.005))
        return False

    def _reader_ready(self) -> bool:
        """A reader has had the port for settle_s (its open-time flush is behind it)."""
        if not self._reader_present():
            self._present_since = None
            return False
        now = time.monotonic()
        if self._present_since is None:
            self._present_since = now
        return now - self._present_since >= self.settle_s

    def _await_reader(self) -> bool:
        """Fast mode: wait until a reader is ready; False if stopped."""
        while not self._stop.is_set():
            self._service()
            if self._reader_ready():
                return True
            self._stop.wait(0.005)
        return False

    #: keep answering the host after the last sample until close() (an adapter stays plugged in)
    serve_after_end = False

    def _run(self) -> None:
        try:
            self._loop()
            if not self._stop.is_set():
                self._drain(self.drain_timeout_s)
                if self.close_at_end:
                    self._sleep_until(time.monotonic() + self.close_grace_s)
                    with self._lock:
                        self._close_port()
        except BaseException as e:            # reported through wait(); the thread must not die silently
            self.error = e
        finally:
            self.done.set()
        if self.serve_after_end and not self.close_at_end and self.error is None:
            while not self._stop.is_set():
                with self._lock:
                    self._service()
                self._stop.wait(0.005)

    def _loop(self) -> None:
        unit = self.unit
        n = unit.n_samples
        rate = unit.rate_hz * unit.config.speed      # samples per second of the wall clock (realtime)
        # outages close the port; silences only stop sending (the unit is quiet, the port stays open)
        outages = sorted([(a, b, "outage") for a, b in unit.outages()]
                         + [(a, b, "silence") for a, b in unit.silences()])
        outages = [o for o in outages if o[1] > self.start_index]
        i = self.start_index
        t0 = time.monotonic() - i / rate          # wall clock of sample 0
        while not self._stop.is_set() and (n is None or i < n):
            if outages and outages[0][0] <= i:
                a, b, kind = outages.pop(0)
                i = self._outage(max(a, i), b, t0) if kind == "outage" else self._silence(max(a, i), b, t0)
                continue
            j = i + self.block_n
            if n is not None:
                j = min(j, n)
            if outages:
                j = min(j, outages[0][0])
            if self.realtime:
                if not self._sleep_until(t0 + j / rate):      # samples [i, j) exist once j / rate has passed
                    break
                if not self._reader_ready():
                    self.record.add_range("no_reader", i, j)
                    i = self.next_index = j
                    continue
            elif not self._reader_ready():
                if not self._await_reader():
                    break
            self._service()
            with self._lock:
                complete = self._send(i, j)
            if not complete:
                self.record.add_range("no_reader", i, j)
            i = self.next_index = j

    def _silence(self, a: int, b: int, t0: float) -> int:
        """The unit sends nothing for samples [a, b), the port open: as long as they last (realtime) or
        faults.silence_s of the wall clock (fast). Returns b."""
        self.record.add_range("silence", a, b)
        if self.realtime:
            self._sleep_until(t0 + b / (self.unit.rate_hz * self.unit.config.speed))
        else:
            self._sleep_until(time.monotonic() + self.unit.config.faults.silence_s)
        self.next_index = b
        return b

    def _outage(self, a: int, b: int, t0: float) -> int:
        """The port closes for samples [a, b): drain, close, wait, reopen. Returns b."""
        self._drain(min(self.drain_timeout_s, 2.0))
        # a reader blocked in read(size, timeout) holds what it got until the call returns, and
        # pyserial throws that away when the port fails: give the call time to return first
        self._sleep_until(time.monotonic() + self.close_grace_s)
        with self._lock:
            self._close_port()
        self.record.add_range("outage", a, b)
        if self.realtime:
            self._sleep_until(t0 + b / (self.unit.rate_hz * self.unit.config.speed))
        else:
            self._sleep_until(time.monotonic() + self.unit.config.faults.outage_s)
        if not self._stop.is_set():
            with self._lock:
                self._open_port()
            self.reconnects += 1
        self.next_index = b
        return b


class _Pty:
    """A pty whose slave is reached through a stable symlink (see the module docstring)."""

    def __init__(self, link_dir: str | None, link_name: str) -> None:
        self._own_dir = link_dir is None
        self.dir = tempfile.mkdtemp(prefix="fluxcal-sim-") if link_dir is None else link_dir
        self.path = os.path.join(self.dir, link_name)
        self.master: int | None = None
        self.pts_path: str | None = None

    def open(self) -> None:
        master, slave = os.openpty()
        # raw on both sides: no echo, no CR/LF translation, no line buffering of binary frames; the
        # settings live with the pty, so a reader that opens the slave later finds them
        tty.setraw(master)
        tty.setraw(slave)
        self.pts_path = os.ttyname(slave)
        os.close(slave)                    # only readers hold the slave: POLLHUP tells us when none does
        os.set_blocking(master, False)
        self.master = master
        tmp = self.path + ".new"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(self.pts_path, tmp)
        os.replace(tmp, self.path)         # atomic re-point: a reader never sees a half-made link

    def close(self) -> None:
        if os.path.lexists(self.path):
            os.unlink(self.path)
        if self.master is not None:
            try:
                os.close(self.master)
            except OSError:
                pass
            self.master = None

    def remove(self) -> None:
        self.close()
        if self._own_dir:
            shutil.rmtree(self.dir, ignore_errors=True)

    def reader_present(self) -> bool:
        if self.master is None:
            return False
        p = select.poll()
        p.register(self.master, select.POLLOUT | select.POLLHUP)
        return not any(ev & select.POLLHUP for _, ev in p.poll(0))

    def unread(self) -> int:
        """Bytes written that the reader has not read yet (FIONREAD on the slave)."""
        if self.master is None or self.pts_path is None:
            return 0
        try:
            fd = os.open(self.pts_path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return 0
        try:
            return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
        finally:
            os.close(fd)

    def read_available(self) -> bytes:
        """What the reader wrote to us (commands), without blocking."""
        if self.master is None:
            return b""
        try:
            return os.read(self.master, 4096)
        except BlockingIOError:
            return b""
        except OSError as e:
            if e.errno == errno.EIO:       # no reader: nothing to read
                return b""
            raise

    def write_all(self, data: bytes | memoryview, stop: threading.Event, service: Any = None) -> bool:
        """Write everything, waiting while the reader's queue is full; False if the reader left or stop."""
        view = memoryview(data)
        while view.nbytes:
            if stop.is_set() or self.master is None:
                return False
            if not self.reader_present():
                return False
            _, writable, _ = select.select([], [self.master], [], 0.02)
            if service is not None:
                service()
            if not writable:
                continue
            try:
                n = os.write(self.master, view[:65536])
            except BlockingIOError:
                continue
            except OSError as e:
                if e.errno == errno.EIO:
                    return False
                raise
            view = view[n:]
        return True

    def drain(self, timeout_s: float, stop: threading.Event, service: Any = None) -> None:
        """Wait until the reader's queue stays empty for 20 ms (bytes just written may still be on
        their way into it), or the reader leaves, or timeout_s."""
        deadline = time.monotonic() + timeout_s
        empty_since: float | None = None
        while time.monotonic() < deadline and not stop.is_set() and self.reader_present():
            if service is not None:
                service()
            now = time.monotonic()
            if self.unread() > 0:
                empty_since = None
            elif empty_since is None:
                empty_since = now
            elif now - empty_since >= 0.02:
                return
            stop.wait(0.002)


class PtyEmitter(Emitter):
    """The unit's serial output (ICD frames, with serial faults) on a pty; readers open `path`.

    >>> from fluxcal.drivers.sim.config import load_sim_config
    >>> from fluxcal.drivers.sim.unit import Unit
    >>> em = PtyEmitter(Unit(load_sim_config({"duration_s": 0.1})))
    >>> em.start().path.endswith("serial")
    True
    >>> em.close()
    """

    label = "serial-pty"

    def __init__(self, unit: Unit, *, link_dir: str | None = None, link_name: str = "serial", **kwargs: Any) -> None:
        super().__init__(unit, **kwargs)
        self._pty = _Pty(link_dir, link_name)

    @property
    def path(self) -> str:
        """The stable path readers open (a symlink to the current /dev/pts/N)."""
        return self._pty.path

    @property
    def pts_path(self) -> str | None:
        return self._pty.pts_path

    def _open_port(self) -> None:
        self._pty.open()

    def _close_port(self) -> None:
        self._pty.close()

    def close(self) -> None:
        super().close()
        self._pty.remove()

    def _reader_present(self) -> bool:
        return self._pty.reader_present()

    def _service(self) -> None:
        self._pty.read_available()           # whatever a reader writes is ignored, never left to pile up

    def _send(self, start: int, stop: int) -> bool:
        data = self.unit.serial_bytes(start, stop, record=self.record)
        return self._pty.write_all(data, self._stop)

    def _drain(self, timeout_s: float) -> None:
        self._pty.drain(timeout_s, self._stop)


def unit_table(unit: Unit) -> dict[str, Any]:
    """The [source] keys a kind's table may take from the simulated unit (a transport's link adds its own)."""
    c = unit.config
    return {"n_probes": c.n_probes, "lsb_nT": c.lsb_nT, "rate_hz": c.rate_hz, "base_id": c.can_base_id}


def pty_link(unit: Unit, *, realtime: bool | None = None, **kwargs: Any) -> tuple[Emitter, dict[str, Any], dict]:
    """The serial kind's "pty" transport (drivers/kinds/serial.py): the unit's ICD bytes on a pty, and the serial
    table that reads them."""
    emitter = PtyEmitter(unit, realtime=realtime, **kwargs).start()
    return emitter, {**unit_table(unit), "port": emitter.path, "baudrate": 921600}, {}


__all__ = ["Emitter", "PtyEmitter", "pty_link", "unit_table"]
