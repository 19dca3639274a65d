"""`fluxcal run --config FILE`: the long-running service (see service/wiring/daemon.py)."""

from __future__ import annotations

import signal
from argparse import Namespace

from service.wiring.config import load_config
from service.wiring.daemon import Daemon


def main(args: Namespace) -> int:
    cfg = load_config(args.config)
    daemon = Daemon(cfg)

    def stop(signum: int, frame: object) -> None:
        daemon.stop.set()                 # the loop notices between blocks, then flushes and closes

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    return daemon.run()
