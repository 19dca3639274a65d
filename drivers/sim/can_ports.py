"""The simulated unit's CAN side: ICD frames on an in-process virtual bus, or as SLCAN lines on a pty the
way a USB-CAN adapter speaks them.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .ports import Emitter, PtyEmitter, unit_table
from .unit import Unit

_HEX = np.frombuffer(b"0123456789ABCDEF", dtype=np.uint8)


class CanEmitter(Emitter):
    """The unit's CAN frames (with can_drop_fraction faults) on a python-can bus.

    Give `bus` to send on a bus of your own, or let the emitter open `interface`/`channel` (default the
    in-process virtual bus "fluxcal-sim"). On a virtual bus a fast emitter waits until another bus has
    joined the channel (frames sent before then reach nobody). An outage is the bus falling silent."""

    label = "can-bus"

    def __init__(self, unit: Unit, *, bus: Any = None, interface: str = "virtual", channel: str = "fluxcal-sim",
                 **kwargs: Any) -> None:
        super().__init__(unit, **kwargs)
        self._given_bus = bus
        self.interface = interface
        self.channel = channel
        self.bus: Any = bus
        self.frames_sent = 0

    def _open_port(self) -> None:
        if self.bus is None:
            import can

            self.bus = can.Bus(interface=self.interface, channel=self.channel, receive_own_messages=False)

    def _close_port(self) -> None:
        # the bus stays up across an outage (the unit is silent, the bus is not gone)
        pass

    def close(self) -> None:
        super().close()
        if self.bus is not None and self._given_bus is None:
            self.bus.shutdown()
            self.bus = None

    def _reader_present(self) -> bool:
        if self.interface != "virtual" or self._given_bus is not None:
            return True
        try:
            from can.interfaces import virtual

            return len(virtual.channels.get(self.channel, [])) > 1
        except (ImportError, AttributeError):
            return True

    def _send(self, start: int, stop: int) -> bool:
        import can

        ids, payloads, _ = self.unit.can_frames(start, stop, record=self.record)
        bus, raw = self.bus, payloads.tobytes()
        for m, arb in enumerate(ids.tolist()):      # python-can sends one message per call
            if self._stop.is_set():
                return False
            bus.send(can.Message(arbitration_id=arb, data=raw[8 * m:8 * m + 8], is_extended_id=False))
            self.frames_sent += 1
        return True


def slcan_lines(ids: np.ndarray, payloads: np.ndarray) -> bytes:
    """Standard frames as SLCAN text, all at once: 't' + 3 hex id + '8' + 16 hex data + CR.

    >>> slcan_lines(np.array([0x201]), np.arange(8, dtype=np.uint8)[None, :])
    b't20180001020304050607\\r'
    """
    m = ids.shape[0]
    out = np.empty((m, 22), dtype=np.uint8)
    out[:, 0] = ord("t")
    ids = np.asarray(ids, dtype=np.int64)
    out[:, 1] = _HEX[(ids >> 8) & 0xF]
    out[:, 2] = _HEX[(ids >> 4) & 0xF]
    out[:, 3] = _HEX[ids & 0xF]
    out[:, 4] = ord("8")
    p = np.asarray(payloads, dtype=np.uint8)
    out[:, 5:21:2] = _HEX[p >> 4]
    out[:, 6:22:2] = _HEX[p & 0xF]
    out[:, 21] = ord("\r")
    return out.tobytes()


class SlcanEmitter(PtyEmitter):
    """An SLCAN USB-CAN adapter on a pty, carrying the unit's CAN frames: open it with
    `can.Bus(interface="slcan", channel=emitter.path, bitrate=1000000, sleep_after_open=0)`.

    Answers the Lawicel commands python-can sends: S0-S8 / s (bit rate), O / L (open), C (close),
    V (version), N (serial number), F (status), Z (timestamps), Y (data bit rate), frames from the
    host (acknowledged 'z'/'Z', counted, not forwarded); '\\r' acknowledges, BEL refuses. Frames flow
    only while the channel is open."""

    label = "slcan-adapter"
    serve_after_end = True
    VERSION = "V1013"
    SERIAL = "NSIM1"

    def __init__(self, unit: Unit, *, link_dir: str | None = None, link_name: str = "slcan", **kwargs: Any) -> None:
        super().__init__(unit, link_dir=link_dir, link_name=link_name, **kwargs)
        self._inbox = bytearray()
        self.channel_open = False
        self.bitrate_cmd: str | None = None
        self.commands: list[str] = []       # every command received, for tests and logs
        self.host_frames = 0

    def _open_port(self) -> None:
        super()._open_port()
        self._inbox.clear()
        self.channel_open = False           # a new adapter starts closed

    def _close_port(self) -> None:
        super()._close_port()
        self.channel_open = False

    def _reader_present(self) -> bool:
        return self._pty.reader_present() and self.channel_open

    def _reply(self, text: bytes) -> None:
        if self._pty.master is not None:
            try:
                os.write(self._pty.master, text)
            except OSError:
                pass

    def _service(self) -> None:
        data = self._pty.read_available()
        if not data:
            return
        self._inbox.extend(data)
        while True:
            cut = self._inbox.find(b"\r")
            if cut < 0:
                if len(self._inbox) > 1024:        # garbage without CR: drop it
                    self._inbox.clear()
                return
            line = bytes(self._inbox[:cut]).decode("ascii", "replace")
            del self._inbox[:cut + 1]
            self._command(line)

    def _command(self, line: str) -> None:
        self.commands.append(line)
        c = line[:1]
        if line == "":
            self._reply(b"\r")
        elif (c == "S" and len(line) == 2 and line[1] in "0123456789") or (c == "s" and len(line) == 5):
            self.bitrate_cmd = line          # nominal bit rate: standard code or BTR registers
            self._reply(b"\r")
        elif c in ("Y", "Z", "W", "M", "m"):  # data bit rate, timestamps, filters: accepted, no effect
            self._reply(b"\r")
        elif c in ("O", "L"):
            self.channel_open = True
            self._reply(b"\r")
        elif c == "C":
            self.channel_open = False
            self._reply(b"\r")
        elif c == "V":
            self._reply(self.VERSION.encode() + b"\r")
        elif c == "v":
            self._reply(b"v" + self.VERSION[1:].encode() + b"\r")
        elif c == "N":
            self._reply(self.SERIAL.encode() + b"\r")
        elif c == "F":
            self._reply(b"F00\r")
        elif c in ("t", "r"):
            self.host_frames += 1
            self._reply(b"z\r" if self.channel_open else b"\a")
        elif c in ("T", "R"):
            self.host_frames += 1
            self._reply(b"Z\r" if self.channel_open else b"\a")
        else:
            self._reply(b"\a")

    def _send(self, start: int, stop: int) -> bool:
        ids, payloads, _ = self.unit.can_frames(start, stop, record=self.record)
        return self._pty.write_all(slcan_lines(ids, payloads), self._stop, self._service)

    def _drain(self, timeout_s: float) -> None:
        self._pty.drain(timeout_s, self._stop, self._service)


def virtual_link(unit: Unit, *, realtime: bool | None = None, channel: str = "",
                 **kwargs: Any) -> tuple[Emitter, dict[str, Any], dict]:
    """The CAN kind's "can-virtual" transport (drivers/kinds/can.py): the unit's ICD frames on python-can's virtual
    bus, and the CAN table that reads them (the emitter starts once the reader's bus has joined)."""
    channel = channel or f"fluxcal-sim-{id(unit):x}"
    emitter = CanEmitter(unit, realtime=realtime, interface="virtual", channel=channel, **kwargs)
    return emitter, {**unit_table(unit), "interface": "virtual", "channel": channel, "bitrate": 1000000}, {}


def slcan_link(unit: Unit, *, realtime: bool | None = None, **kwargs: Any) -> tuple[Emitter, dict[str, Any], dict]:
    """The CAN kind's "slcan" transport: an SLCAN adapter on a pty carrying the unit's ICD frames, and the CAN
    table that reads it through python-can's slcan interface."""
    emitter = SlcanEmitter(unit, realtime=realtime, **kwargs).start()
    table = {**unit_table(unit), "interface": "slcan", "channel": emitter.path, "bitrate": 1000000}
    # python-can waits 2 s after opening an SLCAN tty for a real adapter to boot; ours is ready
    return emitter, table, {"bus_kwargs": {"sleep_after_open": 0}}
