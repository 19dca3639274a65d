"""The Zenoh bus: what the service publishes, answers and obeys (server), and what clients hear (client).

By concern: settings (configuration and security: endpoints, TLS, access control, opening a
session), keys (the key space, the stream encodings and the commands), server (ServiceBus, the
service's side) and client (BusClient, discover_units). Users import from here.
"""

from .zenoh_bus import *  # noqa: F401,F403 - split by concern in the modules named above
from .zenoh_bus import __all__  # noqa: F401
