"""`fluxcal run --config FILE [--dashboard [HOST:PORT]]`: the long-running service (see
service/wiring/daemon.py), and on request the web dashboard beside it in a process of its own (so that
the page costs the service only one more Zenoh subscriber)."""

from __future__ import annotations

import os

# The estimator and the gate multiply small matrices: idle OpenBLAS worker threads spin for the cores between
# them (bench/bench_service.py --live-only, 4 probes at 1 kHz, 30 s: 15.3 % of a core with the default threads
# and the other core busy, 13.3 % with one; idle, 16.9 % and 15.9 %). One thread unless the user says
# otherwise; this only takes effect when numpy is not loaded yet (the CLI).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from argparse import Namespace  # noqa: E402

from fluxcal.drivers.errors import FluxcalError  # noqa: E402
from fluxcal.service.wiring.commands.options import CommandHelp  # noqa: E402
from fluxcal.service.wiring.config import load_config  # noqa: E402
from fluxcal.service.wiring.daemon import Daemon  # noqa: E402

HELP = CommandHelp("run the service: source -> calibration -> Zenoh and MCAP",
                   "  fluxcal run --config configs/sim-gradiometer.toml   # saves to state/, records to "
                   "recordings/live/\n"
                   "                                                      # (its paths are ../state, ../recordings: "
                   "relative to configs/)",
                   more=(" Paths in the configuration ([calibration] file, [mcap] dir) are relative to the configuration file."
                   " It runs until Ctrl-C or SIGTERM (a clean stop: files finished and closed), or for [source] run_s"
                   " seconds on the simulated unit. A calibration saved by an earlier run of the same unit and source kind is"
                   " reloaded at start (its path is said); delete that file to learn afresh (`fluxcal command reset` makes a"
                   " running service forget what it learned). Status lines, gate reasons and commands go to stderr every"
                   " [unit] status_s seconds; recordings to [mcap] dir."))


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, metavar="FILE", help="the service's TOML configuration (required)")
    p.add_argument("--dashboard", nargs="?", const="127.0.0.1:8090", default=None, metavar="HOST:PORT",
                   help="also serve the web dashboard (`fluxcal dashboard`, a process of its own) at HOST:PORT "
                        "(default: 127.0.0.1:8090) and open it in this host's browser if it has one")


def start_dashboard(config: str, listen: str) -> subprocess.Popen:
    """`fluxcal dashboard --config CONFIG --listen LISTEN --open` as a child process; it says its address."""
    from fluxcal.service.wiring.commands.client import parse_listen

    host, port = parse_listen(listen, "--dashboard")
    if port:                              # a port in use: said before the service starts, naming the option typed
        import socket

        try:
            with socket.create_server((host, port)):
                pass
        except OSError as e:
            why = os.strerror(e.errno) if e.errno else str(e)
            raise FluxcalError(f"--dashboard {listen}: cannot serve there ({why}): another dashboard or program "
                               f"holds the port; give another (--dashboard 127.0.0.1:0 picks a free one)") from None
    return subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "dashboard", "--config", config,
                             "--listen", listen, "--open"], stdin=subprocess.DEVNULL)


def main(args: Namespace) -> int:
    cfg = load_config(args.config)
    daemon = Daemon(cfg)
    dashboard = start_dashboard(args.config, args.dashboard) if getattr(args, "dashboard", None) else None

    def stop(signum: int, frame: object) -> None:
        daemon.stop.set()                 # the loop notices between blocks, then flushes and closes

    # SIGHUP (the terminal or ssh session closed, or `kill -HUP`): a clean stop like SIGTERM, the recording
    # finished and the calibration persisted (docs/recording.md); there is no reload: restart to re-read the config
    before = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        return daemon.run()
    finally:
        for sig, handler in before.items():      # the process's own again (a caller in the same process: a test)
            signal.signal(sig, handler)
        if dashboard is not None:
            dashboard.terminate()
            try:
                dashboard.wait(timeout=10)
            except subprocess.TimeoutExpired:
                dashboard.kill()
