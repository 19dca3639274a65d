"""The fluxcal error tree: every error fluxcal raises on purpose derives from one root.

    FluxcalError
    ├── ConfigError            a configuration key, value or file is wrong (names key, value, allowed)
    ├── DataError (ValueError) input data is malformed: CSV, capture, recording (names file, line, column)
    │   └── RecordingError     an MCAP recording cannot be read or written
    ├── DriverError (OSError)  a serial port or CAN bus failed; the daemon reconnects on it
    │   └── SourceTimeout (TimeoutError)
    ├── NotCalibratedError     a calibration is needed and none is usable
    └── CalibrationRefused     the data cannot determine the calibration (says why and what to do)

The command line maps ConfigError, DataError and CalibrationRefused to exit status 2,
every other FluxcalError to 1, and prints the message on one line.
"""

from __future__ import annotations


class FluxcalError(Exception):
    """Root of every error fluxcal raises on purpose."""


class ConfigError(FluxcalError):
    """A configuration key, value or file is wrong."""


class DataError(FluxcalError, ValueError):
    """Input data (CSV, capture, recording, calibration file) is malformed."""


class RecordingError(DataError):
    """An MCAP recording cannot be read or written."""


class DriverError(FluxcalError, OSError):
    """A serial port or CAN bus failed (pulled cable, closed pty, bus error)."""


class SourceTimeout(DriverError, TimeoutError):
    """No data arrived within the time allowed."""


class NotCalibratedError(FluxcalError):
    """A calibration is required and none is usable yet."""


class CalibrationRefused(FluxcalError):
    """The data cannot determine a calibration; the message says why and what motion would help."""
