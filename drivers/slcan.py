"""SLCAN, a USB-CAN adapter's text protocol, read defensively: python-can's slcan interface with a line parser
that never raises and a line buffer that never grows without bound; every line that is no frame is counted.

    t<id:3 hex><len:1 digit><data:2 len hex>[<time:4 hex>]\\r     a standard data frame (T: 8-hex extended id)
    r<id:3 hex><len:1 digit>[<time:4 hex>]\\r                    a remote frame (R: extended)
    d, D, b, B                                                    CAN FD frames (len: one hex digit, DLC code)
    \\r alone                                                     the adapter's OK to a command (not counted)

python-can's own parser raised ValueError or IndexError on one garbled line (`t200F0000000000000000`, `t2008ZZ...`,
`t20`), which stopped `fluxcal run`, and dropped lines it did not know without a count. Here a line is a frame
(a can.Message) or is counted in `bad_lines`: a garbled line, a line the adapter never sends, a line longer than
any frame (its bytes are dropped as they come, so a stream without line ends holds no memory), or the adapter's
error bell. python-can's private `_read`/`_recv_internal` are overridden (python-can 4.x).
"""

from __future__ import annotations

import re
import time
from typing import Any

import can
from can.interfaces.slcan import slcanBus
from can.util import CAN_FD_DLC

#: the longest line a frame takes: 'D' + 8 id + 1 len + 128 data + 4 time stamp
MAX_LINE = 1 + 8 + 1 + 2 * 64 + 4
#: frames read before the bus holds to the adapter's one form, with time stamps or without (the form most of them
#: had): an adapter sends one or the other, so a line of the other form is garbled (four characters doubled in a
#: stamp-less stream read as data and a stamp: a probe's temperature of 59.5 degC recorded where 22.0 was sent)
STAMP_LOCK_FRAMES = 16
_HEX = re.compile(r"[0-9A-Fa-f]*")
#: first letter -> (id digits, extended, remote, FD, bitrate switch)
_KINDS = {"t": (3, False, False, False, False), "T": (8, True, False, False, False),
          "r": (3, False, True, False, False), "R": (8, True, True, False, False),
          "d": (3, False, False, True, False), "D": (8, True, False, True, False),
          "b": (3, False, False, True, True), "B": (8, True, False, True, True)}


def parse_line(line: str) -> can.Message | None:
    """The frame an SLCAN line carries (its terminator stripped or not), or None when it is none: a line that
    does not parse whole is never half taken.

    >>> parse_line("t2018DEADBEEF00000000\\r").data.hex(), parse_line("t2008ZZ"), parse_line("t20")
    ('deadbeef00000000', None, None)
    """
    body = line.rstrip("\r")
    kind = _KINDS.get(body[:1])
    if kind is None:
        return None
    n_id, extended, remote, fd, brs = kind
    ident, code, rest = body[1:1 + n_id], body[1 + n_id:2 + n_id], body[2 + n_id:]
    if len(ident) != n_id or not _HEX.fullmatch(ident) or len(code) != 1 or not _HEX.fullmatch(rest):
        return None
    arbitration_id = int(ident, 16)
    if arbitration_id > (0x1FFFFFFF if extended else 0x7FF):
        return None
    if fd:
        length = CAN_FD_DLC[int(code, 16)]
    elif code.isdigit() and int(code) <= 8:
        length = int(code)
    else:
        return None
    data_chars = 0 if remote else 2 * length
    if len(rest) not in (data_chars, data_chars + 4):            # the data, then perhaps a time stamp
        return None
    return can.Message(arbitration_id=arbitration_id, is_extended_id=extended, is_remote_frame=remote,
                       is_fd=fd, bitrate_switch=brs, dlc=length, data=bytes.fromhex(rest[:data_chars]),
                       timestamp=time.time())


def stamped_line(line: str, msg: can.Message) -> bool:
    """Whether the line of frame `msg` (parse_line's) ends in a time stamp.

    >>> line = "t2018DEADBEEF000000001234"
    >>> stamped_line(line, parse_line(line)), stamped_line(line[:-4], parse_line(line[:-4]))
    (True, False)
    """
    data_chars = 0 if msg.is_remote_frame else 2 * msg.dlc
    return len(line.rstrip("\r")) == 2 + (8 if msg.is_extended_id else 3) + data_chars + 4


class SlcanBus(slcanBus):
    """python-can's slcan interface, reading with `parse_line` (see the module docstring); `bad_lines` counts
    the lines that are no frame."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.bad_lines = 0
        self._forms = [0, 0]             # frames read without and with a time stamp, until STAMP_LOCK_FRAMES
        self._line = bytearray()
        self._overlong = False           # the line being read passed MAX_LINE: dropped up to its end
        super().__init__(*args, **kwargs)

    def _read(self, timeout: float | None) -> str | None:
        """The next line, its terminator included (\\r, or the error bell \\a), or None when none came in time."""
        import serial

        deadline = serial.Timeout(timeout)
        port = self.serialPortOrig
        try:
            while True:
                for _ in range(max(1, port.in_waiting)):
                    byte = port.read(1)
                    if not byte:
                        break
                    if byte in (self._OK, self._ERROR):
                        line, overlong = self._line.decode("latin-1") + byte.decode("latin-1"), self._overlong
                        self._line.clear()
                        self._overlong = False
                        if not overlong:
                            return line
                        continue                     # counted when it passed MAX_LINE
                    if self._overlong:
                        continue
                    self._line += byte
                    if len(self._line) > MAX_LINE:
                        self.bad_lines += 1
                        self._overlong = True
                        self._line.clear()
                if deadline.expired():
                    return None
        except (serial.SerialException, OSError) as e:
            raise can.CanOperationError(f"Could not read from serial device: {e}") from e

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        queued = getattr(self, "_queue", None)
        line = queued.get_nowait() if queued is not None and queued.qsize() else self._read(timeout)
        if not line or line == "\r":          # nothing, or the adapter's OK to a command
            return None, False
        msg = parse_line(line) if line.endswith("\r") else None       # \a: the adapter's error bell
        if msg is not None:
            stamped = int(stamped_line(line, msg))
            if sum(self._forms) < STAMP_LOCK_FRAMES:
                self._forms[stamped] += 1
            elif self._forms[stamped] < self._forms[1 - stamped]:
                msg = None                       # the other form than the adapter's: garbled
        if msg is None:
            self.bad_lines += 1
        return msg, False
