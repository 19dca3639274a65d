"""`fluxcal dashboard`: a web dashboard that subscribes to units over Zenoh (hub), keeps what the page
shows (view, history) and serves it (server, static/)."""

from .hub import Hub
from .server import DashboardServer

__all__ = ["DashboardServer", "Hub"]
