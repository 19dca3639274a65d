"""Moved to service.io.recordings; these names stay importable from here for code written against 0.1."""

from service.io.recordings.reader import FluxcalDecoderFactory, Recording, read_recording, repair_recording  # noqa: F401
