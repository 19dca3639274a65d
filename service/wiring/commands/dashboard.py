"""`fluxcal dashboard`: the web dashboard of running units (fluxcal.service.wiring.dashboard)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Any

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.wiring.commands.client import parse_listen, resolve_units
from fluxcal.service.wiring.commands.options import CommandHelp, client_options

HELP = CommandHelp("web dashboard of running units: live plots with history, coverage, "
                   "calibration, health, diagnosis and commands, served on this host",
                   "  fluxcal dashboard --config configs/sim-gradiometer.toml --open\n"
                   "  fluxcal dashboard --connect tcp/10.0.0.5:7447 --unit grad1 --unit grad2 --listen 0.0.0.0:8090",
                   more=(" It subscribes over Zenoh like `watch` (lossily: it never holds a unit back) and serves a"
                   " page at --listen; the plot code comes from the package, no internet needed. Ctrl-C stops"
                   " it."))


def add_options(p: argparse.ArgumentParser) -> None:
    client_options(p, "dashboard")
    p.add_argument("--listen", default="127.0.0.1:8090", metavar="HOST:PORT",
                   help="where the page is served (default: %(default)s, this host only; port 0: a free one, said "
                        "at start)")
    p.add_argument("--open", action="store_true", help="open the page in this host's web browser")
    p.add_argument("--read-only", dest="read_only", action="store_true",
                   help="show, but send no commands and run no diagnosis (for a page served beyond this host)")


def _open(url: str) -> None:
    """Open the page in this host's browser; on a host without a display (a terminal browser would take the
    terminal) say where it is instead."""
    import os
    import webbrowser

    graphical = sys.platform in ("darwin", "win32") or os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if not (graphical and webbrowser.open(url)):
        print(f"fluxcal dashboard: no browser to open here; open {url} in a browser on this host (or forward the "
              f"port: ssh -L {url.rsplit(':', 1)[1].strip('/')}:127.0.0.1:{url.rsplit(':', 1)[1].strip('/')} HOST)",
              file=sys.stderr, flush=True)


def config_geometry(path: str) -> dict[str, Any]:
    """{unit name: Geometry} of a service configuration: its unit's probe positions and total field, which the
    dashboard's diagnosis needs as `fluxcal diagnose --config` does (a unit's state does not carry them)."""
    from fluxcal.service.wiring.config import load_config
    from fluxcal.service.wiring.dashboard.hub import Geometry
    from fluxcal.service.wiring.prepare import config_geometry as read_geometry
    from fluxcal.service.wiring.prepare import spread

    cfg = load_config(path)
    positions, total = read_geometry(path, cfg.unit.n_probes)
    return {cfg.unit.name: Geometry(spread(positions), total, path)}     # probes at one point: no positions, as fit


def main(args: argparse.Namespace) -> int:
    from fluxcal.service.wiring.dashboard import DashboardServer, Hub

    endpoints, units, tls = resolve_units(args)
    host, port = parse_listen(args.listen)
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise ConfigError(f"--seconds: {args.seconds!r} is not allowed (allowed: a positive number of seconds)")
    geometry = config_geometry(args.config) if getattr(args, "config", None) else None
    hub = Hub(endpoints, units, tls, geometry).start()
    try:
        server = DashboardServer(hub, host, port, read_only=args.read_only, say_refusals=True)
    except OSError as e:
        hub.close()
        raise ConfigError(f"--listen: cannot serve on {args.listen}: {e.strerror or e}") from None
    server.start()
    print(f"fluxcal dashboard: {server.url} (units: {', '.join(units) if units else 'every unit found'} via "
          f"{', '.join(endpoints)}){'; read-only' if args.read_only else ''}", file=sys.stderr, flush=True)
    if host not in ("127.0.0.1", "localhost", "::1") and not args.read_only:
        print("fluxcal dashboard: anyone who reaches this address and loads the page can send the units commands "
              "(other web pages cannot: Host, Origin and the page's token are checked); use --read-only or a "
              "loopback address behind an authenticating proxy", file=sys.stderr, flush=True)
    if args.open:
        _open(server.url)
    try:
        deadline = None if args.seconds is None else time.monotonic() + args.seconds
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        import signal

        # a second signal must not cut the closing short; then the process's own handlers again (a caller in the
        # same process, a test, would be left deaf to Ctrl-C)
        before = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            server.stop()
            hub.close()
        finally:
            for sig, handler in before.items():
                signal.signal(sig, handler)
    return 0
