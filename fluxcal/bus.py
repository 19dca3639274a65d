"""The service's streams and commands on Eclipse Zenoh from Python (docs/zenoh.md): a client of a running unit.

>>> from fluxcal.bus import BusClient, ZenohConfig
>>> ZenohConfig().mode
'peer'
"""

from fluxcal.service.io.bus import BusClient, Message, ZenohConfig, discover_units

__all__ = ["BusClient", "Message", "ZenohConfig", "discover_units"]
