"""`fluxcal run --config FILE [--dashboard [HOST:PORT]]`: the long-running service (see
service/wiring/daemon.py), and on request the web dashboard beside it in a process of its own (so that
the page costs the service only one more Zenoh subscriber)."""

from __future__ import annotations

import signal
import subprocess
import sys
from argparse import Namespace

from service.wiring.config import load_config
from service.wiring.daemon import Daemon


def start_dashboard(config: str, listen: str) -> subprocess.Popen:
    """`fluxcal dashboard --config CONFIG --listen LISTEN --open` as a child process; it says its address."""
    from service.wiring.commands.watch import parse_listen

    parse_listen(listen, "--dashboard")
    return subprocess.Popen([sys.executable, "-m", "service.wiring.cli", "dashboard", "--config", config,
                             "--listen", listen, "--open"], stdin=subprocess.DEVNULL)


def main(args: Namespace) -> int:
    cfg = load_config(args.config)
    daemon = Daemon(cfg)
    dashboard = start_dashboard(args.config, args.dashboard) if getattr(args, "dashboard", None) else None

    def stop(signum: int, frame: object) -> None:
        daemon.stop.set()                 # the loop notices between blocks, then flushes and closes

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    try:
        return daemon.run()
    finally:
        if dashboard is not None:
            dashboard.terminate()
            try:
                dashboard.wait(timeout=10)
            except subprocess.TimeoutExpired:
                dashboard.kill()
