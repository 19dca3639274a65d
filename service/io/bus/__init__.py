"""The Zenoh bus: what the service publishes, answers and obeys, and what clients hear.

By concern: settings (configuration and security: endpoints, TLS, access control, opening a
session), keys (the key space, the stream encodings, the commands), server (ServiceBus, the
service's side), client (BusClient, discover_units). Users import from here.
"""

from .client import BusClient, Message, discover_units
from .keys import COMMANDS, MAX_COMMAND_PAYLOAD_BYTES, STREAMS, Command, Keys, Series, decode_series, encode_series
from .server import ServiceBus
from .settings import (
                       DEFAULT_LISTEN,
                       DEFAULT_PORT,
                       BusError,
                       ZenohAccessConfig,
                       ZenohConfig,
                       ZenohTlsConfig,
                       make_zenoh_config,
                       open_session,
)

__all__ = [
    "BusClient", "BusError", "Command", "COMMANDS", "MAX_COMMAND_PAYLOAD_BYTES", "Keys", "Message", "Series",
    "ServiceBus",
    "STREAMS", "ZenohAccessConfig", "ZenohConfig", "ZenohTlsConfig", "discover_units", "make_zenoh_config", "open_session",
    "decode_series", "encode_series", "DEFAULT_PORT", "DEFAULT_LISTEN",
]
