"""Moved to service.io.bus; these names stay importable from here for code written against 0.1."""

from service.io.bus import BusClient, BusError, Keys, Message, Series, ZenohConfig, decode_series, encode_series  # noqa: F401
